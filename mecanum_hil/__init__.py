"""mecanum-hil: hardware-in-the-loop bridge and data acquisition for Mecanum-wheeled robots."""

__version__ = "0.1.0"
