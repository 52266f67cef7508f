"""The CRTK controller (:class:`Controller`): the logic of the control process, split along its
concerns -- ``controller`` (the facade: state, requests, motion, the cycle's step),
``transitions``, ``supervisor``, ``relays``, ``park``, ``validation``."""

from .common import MOTION_COMMANDS, STATE_COMMANDS, Refused
from .controller import Controller

__all__ = ["Controller", "Refused", "MOTION_COMMANDS", "STATE_COMMANDS"]
