"""Universal Robots arms over RTDE (ur_rtde); see backend.py."""
