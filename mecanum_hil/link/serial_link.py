"""The serial transport: COBS frames with CRC over anything pyserial opens, or a raw fd.

Writes never block: a frame the operating system cannot take at once waits in a small
output buffer that is pushed on every later send/receive; when that buffer overflows the
frame is dropped and counted (``send_errors``) rather than stalling the caller. A blocking
writer deadlocked on bursts when a pseudo-terminal's buffer filled on these machines.
"""

from __future__ import annotations

import errno
import os
import select
import time
from collections import deque
from typing import Any

import numpy as np

from ..errors import LinkError, LinkLostError
from .protocol import Command, Message, Stop, StreamDecoder, encode
from .transport import Transport

#: Largest amount of unsent output kept before frames are dropped [bytes].
MAX_PENDING_BYTES = 16384


class PendingOutput:
    """Bytes on their way out through a writer that never blocks.

    Parameters
    ----------
    write : callable
        Takes bytes, returns how many it took; raises ``BlockingIOError`` when it takes none
        now and ``OSError`` when the device is gone.
    where : str
        Port name for error messages.
    limit : int
        Largest backlog [bytes]; beyond it :meth:`queue` refuses the data.
    """

    def __init__(self, write, where: str, limit: int = MAX_PENDING_BYTES) -> None:
        self._write = write
        self.where = where
        self.limit = limit
        self._buf = bytearray()

    def queue(self, data: bytes) -> None:
        """Add ``data`` and push what the device takes now."""
        self.flush()
        if len(self._buf) + len(data) > self.limit:
            raise LinkError(f"{self.where}: output buffer full, the other side does not read")
        self._buf += data
        self.flush()

    def urgent(self, data: bytes, resync: bytes = b"") -> None:
        """Send ``data`` before anything pending: the backlog (stale commands) is dropped.

        ``resync`` goes first when a partly written message may be cut off, so the receiver
        finds the start of ``data`` (a frame delimiter, a line end).
        """
        if self._buf:
            self._buf = bytearray(resync)
        self._buf += data
        self.flush()

    def flush(self) -> None:
        """Push what the device takes now; keep the rest."""
        if not self._buf:
            return
        try:
            n = self._write(bytes(self._buf))
        except BlockingIOError:
            return
        except OSError as err:
            raise LinkLostError(f"{self.where}: link lost while writing: {err}") from err
        del self._buf[:n or 0]


def _check_network_url(port: str) -> None:
    """A one-line error for a ``socket://`` or ``rfc2217://`` URL without a usable host and
    port: pyserial's own errors for them are its URL parser's ("'debug|info|warning|error'",
    a comparison with None)."""
    from urllib.parse import urlsplit

    scheme = port.partition("://")[0].lower() if "://" in port else ""
    if scheme not in ("socket", "rfc2217"):
        return
    try:
        parts = urlsplit(port)
        ok = bool(parts.hostname) and parts.port is not None and 0 < parts.port < 65536
    except ValueError:
        ok = False
    if not ok:
        raise LinkError(f"{port}: not a network port: give {scheme}://HOST:PORT with a port "
                        "number 1-65535")


class SerialTransport(Transport):
    """Framed protocol over a serial port (``/dev/ttyUSB0``, ``loop://``, ``socket://...``).

    Parameters
    ----------
    port : str, optional
        Anything :func:`serial.serial_for_url` opens.
    baudrate : int
        Line rate [bit/s] (ignored by pseudo-terminals, which carry bytes at memory speed).
    fd : int, optional
        Instead of ``port``: an open file descriptor (e.g. a pseudo-terminal's master side),
        used as it is and closed with the transport.
    """

    name = "serial"
    seq_modulus = 1 << 16

    def __init__(self, port: str | None = None, baudrate: int = 1_000_000,
                 fd: int | None = None) -> None:
        super().__init__()
        if (port is None) == (fd is None):
            raise LinkError("serial transport: give exactly one of port and fd")
        self.port = port if port is not None else f"fd {fd}"
        self._ser = None
        self._decoder = StreamDecoder()
        self._inbox: deque[tuple[Message, int]] = deque()
        self._out = PendingOutput(self._write, self.port)
        if fd is not None:
            os.set_blocking(fd, False)
            self._fd: int | None = fd
            return
        _check_network_url(port)
        import serial

        try:
            # pyserial flushes the input at open: bytes sent before are lost (hence HELLO)
            self._ser = serial.serial_for_url(port, baudrate=int(baudrate), timeout=0,
                                              write_timeout=0.05)
        except (serial.SerialException, ValueError, OSError) as err:
            raise LinkError(f"{port}: cannot open serial port: {err}") from err
        try:
            self._fd = self._ser.fileno()
        except Exception:  # loop:// and some URL handlers have no descriptor: poll them
            self._fd = None

    @classmethod
    def from_options(cls, port: str | None = None, baudrate: Any = 1_000_000,
                     **extra: Any) -> SerialTransport:
        if port is None:
            raise LinkError("the serial transport needs --port PORT")
        if extra:
            raise TypeError(f"unknown options: {', '.join(sorted(extra))}")
        return cls(port=port, baudrate=int(baudrate))

    def wire_command(self, n_rpm: float, omega_dps: float, theta_deg: float) -> Command:
        f32 = np.float32
        return Command(float(f32(n_rpm)), float(f32(omega_dps)), float(f32(theta_deg)))

    # -- hooks -------------------------------------------------------------------------------
    def _send(self, msg: Message) -> None:
        if isinstance(msg, Stop):
            # STOP never waits behind a backlog of older commands
            self._out.urgent(encode(msg), resync=b"\x00")
        else:
            self._out.queue(encode(msg))

    def send_raw(self, data: bytes) -> None:
        """Queue ``data`` (bytes, framed or not) for the wire as it is (conformance tests)."""
        self._out.queue(bytes(data))

    def _write(self, data: bytes) -> int:
        if self._fd is not None:
            return os.write(self._fd, data)
        try:
            return self._ser.write(data) or 0
        except Exception as err:  # serial.SerialException (pyserial imported lazily)
            if type(err).__name__ == "SerialTimeoutException":
                raise BlockingIOError from err  # nothing taken now: stays pending
            raise OSError(str(err)) from err

    def _read_available(self, timeout_s: float) -> bytes:
        if self._fd is None:
            try:
                data = self._ser.read(4096)
            except Exception as err:
                raise LinkLostError(f"{self.port}: link lost while reading: {err}") from err
            if not data and timeout_s > 0:
                time.sleep(min(timeout_s, 0.0005))
            return data
        try:
            ready, _, _ = select.select([self._fd], [], [], timeout_s)
        except (OSError, ValueError) as err:
            raise LinkLostError(f"{self.port}: link lost: {err}") from err
        if not ready:
            return b""
        try:
            data = os.read(self._fd, 65536)
        except BlockingIOError:
            return b""
        except OSError as err:
            # EIO: the other side of a pseudo-terminal closed; ENXIO/ENODEV: USB unplugged
            if err.errno in (errno.EIO, errno.ENXIO, errno.ENODEV, errno.EBADF):
                raise LinkLostError(f"{self.port}: link lost (the device went away)") from err
            raise LinkLostError(f"{self.port}: link lost while reading: {err}") from err
        if not data:
            raise LinkLostError(f"{self.port}: link lost (end of file)")
        return data

    def _recv(self, timeout_s: float) -> Message | None:
        deadline = time.monotonic() + timeout_s
        while not self._inbox:
            self._out.flush()
            remaining = deadline - time.monotonic()
            data = self._read_available(max(0.0, remaining))
            if data:
                self._inbox.extend(self._decoder.feed_counted(data))
                self._sync_counts()
            if not self._inbox and remaining <= 0:
                return None
        msg, drops = self._inbox.popleft()
        self._dropped(drops)
        return msg

    def _sync_counts(self) -> None:
        c = self._decoder.counts
        s = self.stats
        s.crc_errors, s.malformed, s.unknown_types = c.crc, c.malformed, c.unknown_type
        s.version_errors, s.garbage_bytes = c.version, c.garbage_bytes
        while self._decoder.rejected:
            self.rejected.append(self._decoder.rejected.popleft())

    def _close(self) -> None:
        try:
            self._out.flush()
        except LinkError:
            pass
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # closing a port that vanished must not mask the real error
                pass
        elif self._fd is not None:
            try:
                os.close(self._fd)
            except OSError:
                pass
