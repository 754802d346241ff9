"""A simulated SLCAN (Lawicel) adapter: the controller's CAN end behind a pseudo-terminal.

Linux vcan is not available everywhere and python-can's ``virtual`` bus is in-process only, so
``sim-robot --slcan`` plays a USB-CAN adapter: the host opens the pseudo-terminal's slave side
with python-can's ``slcan`` interface (``--interface slcan --channel /dev/pts/N
--link-option sleep_after_open=0``) and the frames it transmits arrive here as ``tIIILDD..``
lines, decoded with the same DBC codec as any CAN bus; the controller's frames go back the
same way. Writes never block (a blocking writer deadlocked on bursts when the pty filled).
"""

from __future__ import annotations

import errno
import os
import select
import time
from collections import deque

from ..errors import LinkLostError
from .can_link import CanCodec, count_frame_error
from .protocol import FrameError, Message, Stop
from .serial_link import PendingOutput
from .transport import Transport

# answers to adapter commands: C close, S/s bitrate, O open, L listen-only, V/v version,
# N serial number, F status flags, Z timestamps, M/m acceptance filter; '' (bare CR) is a no-op
_REPLIES = {"V": b"V1013\r", "v": b"vSTM32\r", "N": b"NSIM1\r", "F": b"F00\r"}


class SlcanAdapterTransport(Transport):
    """The controller's end of a CAN link, speaking SLCAN on a file descriptor.

    Parameters
    ----------
    fd : int
        The pseudo-terminal's master side (closed with the transport).
    """

    name = "slcan-adapter"
    seq_modulus = 1 << 8

    def __init__(self, fd: int) -> None:
        super().__init__()
        os.set_blocking(fd, False)
        self.fd = fd
        self.port = f"slcan fd {fd}"
        self.opened = False
        self.commands_seen: list[str] = []
        self._codec = CanCodec()
        self._line = bytearray()
        self._inbox: deque[Message] = deque()
        self._out = PendingOutput(lambda data: os.write(fd, data), "slcan adapter", 32768)

    def wire_command(self, n_rpm, omega_dps, theta_deg):
        return self._codec.wire_command(n_rpm, omega_dps, theta_deg)

    def _queue(self, data: bytes) -> None:
        self._out.queue(data)

    def _send(self, msg: Message) -> None:
        if not self.opened:
            return  # a closed adapter puts nothing on the bus
        lines = b"".join(f"t{fid:03X}{len(data)}{data.hex().upper()}\r".encode()
                         for fid, data in self._codec.encode(msg))
        if isinstance(msg, Stop):
            self._out.urgent(lines, resync=b"\r")  # STOP never waits behind a backlog
        else:
            self._queue(lines)

    def _line_in(self, line: str) -> None:
        if not line:
            self._queue(b"\r")
            return
        head = line[0]
        self.commands_seen.append(line if head not in "tT" else head)
        if head == "t":
            try:
                fid = int(line[1:4], 16)
                dlc = int(line[4])
                data = bytes.fromhex(line[5:5 + 2 * dlc])
                if len(data) != dlc:
                    raise ValueError("short data")
            except ValueError:
                self.stats.malformed += 1
                self._dropped()
                self._queue(b"\a")
                return
            self._queue(b"z\r")
            if fid >= 0x180 and self.receives is not None:
                self.stats.echoes += 1  # a controller's frame: not for this end
                return
            try:
                msg = self._codec.decode(fid, data)
            except FrameError as err:
                count_frame_error(self, err)
                return
            if msg is not None:
                self._inbox.append(msg)
            return
        if head in "OL":
            self.opened = True
        elif head == "C":
            self.opened = False
        self._queue(_REPLIES.get(head, b"\r"))

    def _recv(self, timeout_s: float) -> Message | None:
        deadline = time.monotonic() + timeout_s
        while not self._inbox:
            self._out.flush()
            remaining = max(0.0, deadline - time.monotonic())
            ready, _, _ = select.select([self.fd], [], [], remaining)
            if ready:
                try:
                    data = os.read(self.fd, 65536)
                except BlockingIOError:
                    data = b""
                except OSError as err:
                    if err.errno == errno.EIO:  # no host has the slave open (yet / any more)
                        time.sleep(min(remaining, 0.01))
                        data = b""
                    else:
                        raise LinkLostError(f"slcan adapter: link lost: {err}") from err
                for byte in data:
                    if byte in (0x0D, 0x0A):
                        self._line_in(self._line.decode("ascii", errors="replace"))
                        self._line.clear()
                    else:
                        self._line.append(byte)
                        if len(self._line) > 64:
                            self.stats.malformed += 1
                            self._line.clear()
            if not self._inbox and deadline - time.monotonic() <= 0:
                return None
        return self._inbox.popleft()

    def _close(self) -> None:
        try:
            os.close(self.fd)
        except OSError:
            pass
