"""CANopen CiA 402 drives (``type: canopen402``): see :mod:`.backend`; the standards as data in
:mod:`.tables`, the standard object dictionary in :mod:`.od`."""
