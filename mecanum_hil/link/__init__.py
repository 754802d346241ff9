"""The robot link (hardware seam): wire protocol, transports, simulated controller, recording.

Heavy pieces (pyserial, python-can, cantools, the simulator) are imported by the submodules
that need them; importing this package is cheap.
"""

from .protocol import PROTOCOL_VERSION, WATCHDOG_S
from .transport import (
    ENTRY_POINT_GROUP,
    TRANSPORTS,
    LinkStats,
    Transport,
    available_transports,
    open_transport,
    transport_class,
)

__all__ = [
    "ENTRY_POINT_GROUP",
    "PROTOCOL_VERSION",
    "TRANSPORTS",
    "WATCHDOG_S",
    "LinkStats",
    "Transport",
    "available_transports",
    "open_transport",
    "transport_class",
]
