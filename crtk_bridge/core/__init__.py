"""Core layer: operating-state machine, motion, limits, the real-time loop. Imports only the
actuator interface (never a backend), the profile and errors."""
