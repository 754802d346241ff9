"""Shadow mode: the fitted model beside the robot, flagging persistent divergence.

:class:`ShadowMonitor` (live, one sample at a time; a link ``TelemetryObserver``) and
:func:`replay` (a recording, as if live) share one compiled per-sample core;
:func:`shadow_fault_demo` is the demo's run with an injected fault that gets flagged.
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
from .scenarios import shadow_fault_demo

__all__ = [
    "CHANNELS",
    "Alarm",
    "ShadowConfig",
    "ShadowMonitor",
    "ShadowResult",
    "recording_rows",
    "replay",
    "shadow_fault_demo",
]
