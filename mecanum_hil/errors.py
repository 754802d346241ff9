"""The one exception tree of mecanum-hil.

Every error the package raises on purpose derives from :class:`MecanumHILError`. Foreign
exceptions (``OSError``, ``serial.SerialException``, ``can.CanError``, ``cv2.error`` ...) are
re-raised as one of these ``from err`` at the edge where they occur, so the CLI can turn any of
them into a single ``error: ...`` line and a non-zero exit code.
"""

from __future__ import annotations


class MecanumHILError(Exception):
    """Root of every error raised by mecanum-hil.

    Attributes
    ----------
    exit_code : int
        Process exit code the CLI uses when this error ends a command.
    """

    exit_code = 1


class ConfigError(MecanumHILError):
    """A robot profile, calibration, profile or effects file is missing or has a bad value."""


class UsageError(ConfigError):
    """The command line names what does not exist (an unknown profile name) or leaves out a
    choice it needs (none of the options of which a command takes one). The CLI ends with 2,
    as for click's own usage errors, and names the command's help."""

    exit_code = 2


class RecordingError(MecanumHILError):
    """A recording (CSV + optional JSON sidecar) is malformed or cannot be read or written."""


class LimitError(MecanumHILError):
    """A command or command profile exceeds the robot profile's limits."""


class LinkError(MecanumHILError):
    """The link to the robot controller failed (port missing or lost, bus error, timeout)."""


class LinkLostError(LinkError):
    """The link went away mid-run (port gone, controller silent or dead)."""

    exit_code = 4


class ProtocolError(LinkError):
    """The controller spoke the wire protocol wrongly (version mismatch, bad hello)."""


class VideoError(MecanumHILError):
    """A video cannot be decoded or gives no trustworthy measurement."""


class FitError(MecanumHILError):
    """Coefficients cannot be estimated from the data given."""


class DiagnoseError(MecanumHILError):
    """The model/measurement disagreement cannot be analysed from the data given."""


class SessionTerminated(BaseException):
    """A signal other than Ctrl-C (SIGTERM, SIGHUP, SIGQUIT ...) ends a command stream: raised
    by its handler, like ``KeyboardInterrupt`` for Ctrl-C, so that it unwinds past ordinary
    ``except Exception`` clauses to the code that sends STOP. The CLI ends with 143."""

    exit_code = 143


class MecanumHILWarning(UserWarning):
    """Something was done to the data that the user should know of (the CLI prints one line)."""
