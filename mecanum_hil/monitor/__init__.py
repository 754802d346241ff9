"""Shadow mode: the fitted model beside the robot, flagging persistent divergence.

:class:`ShadowMonitor` (live, one sample at a time; a link ``TelemetryObserver``) and
:func:`replay` (a recording, as if live) share one compiled per-sample core.
"""

from .core import (
    CHANNELS,
    Alarm,
    ShadowConfig,
    ShadowMonitor,
    ShadowResult,
    recording_rows,
    replay,
)

__all__ = [
    "CHANNELS",
    "Alarm",
    "ShadowConfig",
    "ShadowMonitor",
    "ShadowResult",
    "recording_rows",
    "replay",
]
