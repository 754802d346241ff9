"""Conformance rules of the controller protocol: drive any controller, name the rules it breaks.

Each rule of ``drivers/protocol.md`` ("The controller's duties") is a function that drives
the controller through a :class:`Probe` (the host's end of the link, any
:class:`~mecanum_hil.link.transport.Transport`) and returns what it saw, or raises
:class:`RuleFailedError` naming what was wrong, or :class:`RuleSkippedError` when it cannot run here
(a rule that sends damaged frames needs :meth:`Transport.send_raw`; the e-stop rules need the
e-stop pressed). Every rule starts its own session with a HELLO and ends with STOP, so the
rules are independent and the wheels are stopped between them. :func:`run_conformance` runs
them and returns a :class:`ConformanceReport` (``mecanum-hil conformance`` prints it).

Every verdict names the section and sentence of ``drivers/protocol.md`` it checks. A rule
during which the host's own stream (commands, heartbeats) slipped by more than
:data:`SLIP_S` is run again, up to :data:`ATTEMPTS` times; when every attempt slipped its
outcome is ``inconclusive``, never ``fail``. A rule in which the host could not send (a link
error, the link not lost) runs again too; it fails only when every attempt could not. A
controller announcing no telemetry fails every rule that watches it: without samples nothing
it does can be seen.

The wheels turn (up to the announced limit for a fraction of a second): run it against a real
robot on stands only.
"""

from __future__ import annotations

import itertools
import math
import random
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

from ..errors import LinkError, LinkLostError
from ..model.kinematics import command_to_wheels
from ..model.robot import RobotProfile
from .protocol import (
    PROTOCOL_VERSION,
    STATUS_DEFINED,
    WATCHDOG_S,
    Command,
    ErrorCode,
    ErrorMsg,
    EstopReset,
    Heartbeat,
    Hello,
    HelloAck,
    Message,
    MsgType,
    Ping,
    Pong,
    Status,
    Stop,
    Telemetry,
    cobs_encode,
    crc16,
    pack_frame,
)
from .session import SignalGuard
from .transport import Transport

#: How long an answer (HELLO_ACK, ERROR, PONG, an acknowledging sample) may take [s].
ANSWER_S = 0.3

#: A frame the host streams (``keep``) later than its period plus this is a slip of the
#: host's own timing [s]: 80 ms heartbeats 0.18 s apart still feed a 250 ms watchdog.
SLIP_S = 0.1

#: Attempts of a rule whose own timing slipped before it is reported ``inconclusive``.
ATTEMPTS = 3


class RuleFailedError(Exception):
    """The controller broke the rule; the text says what was seen."""


class RuleSkippedError(Exception):
    """The rule cannot run on this link or setup; the text says why."""


@dataclass(frozen=True)
class RuleResult:
    """The outcome of one rule.

    Attributes
    ----------
    rule : str
        The rule's name (``command.non_finite``, ...).
    outcome : str
        ``"pass"``, ``"fail"``, ``"skip"`` or ``"inconclusive"`` (the host's own timing
        slipped in every attempt: not judged).
    detail : str
        What was seen (pass), what was wrong (fail), why it did not run (skip), or how the
        host's timing slipped (inconclusive).
    duration_s : float
        How long the rule took [s].
    section : str
        The section and sentence of ``drivers/protocol.md`` the rule checks.
    attempts : int
        How many times the rule ran (more than one when the host's timing slipped).
    """

    rule: str
    outcome: str
    detail: str
    duration_s: float
    section: str = ""
    attempts: int = 1


@dataclass(frozen=True)
class ConformanceReport:
    """Every rule's result and what the controller announced."""

    results: tuple[RuleResult, ...]
    controller: str = ""
    announced: dict[str, Any] = field(default_factory=dict)
    link: str = ""

    @property
    def failed(self) -> list[str]:
        """Names of the rules that failed."""
        return [r.rule for r in self.results if r.outcome == "fail"]

    @property
    def inconclusive(self) -> list[str]:
        """Names of the rules not judged (the host's own timing slipped)."""
        return [r.rule for r in self.results if r.outcome == "inconclusive"]

    @property
    def ok(self) -> bool:
        """No rule failed or was inconclusive (and at least one passed)."""
        return (not self.failed and not self.inconclusive
                and any(r.outcome == "pass" for r in self.results))

    def as_dict(self) -> dict[str, Any]:
        """The report as JSON-ready data."""
        counts = {k: sum(r.outcome == k for r in self.results)
                  for k in ("pass", "fail", "skip", "inconclusive")}
        return {"protocol_version": PROTOCOL_VERSION, "link": self.link,
                "controller": self.controller, "announced": self.announced,
                "passed": counts["pass"], "failed": counts["fail"], "skipped": counts["skip"],
                "inconclusive": counts["inconclusive"],
                "ok": self.ok, "rules": [asdict(r) for r in self.results]}

    def format(self) -> str:
        """One line per rule, then a summary line."""
        lines = [f"conformance of {self.controller or 'the controller'} on {self.link} "
                 f"(protocol {PROTOCOL_VERSION})"]
        width = max((len(r.rule) for r in self.results), default=10)
        mark = {"pass": "pass", "fail": "FAIL", "skip": "skip", "inconclusive": "INCONCLUSIVE"}
        for r in self.results:
            lines.append(f"  {mark[r.outcome]}  {r.rule:<{width}}  {r.detail}"
                         + (f" [protocol.md, {r.section}]" if r.section else ""))
        d = self.as_dict()
        lines.append(f"{d['passed']} passed, {d['failed']} failed, {d['skipped']} skipped"
                     + (f", {d['inconclusive']} inconclusive" if d["inconclusive"] else "")
                     + (f": {', '.join(self.failed)}" if self.failed else ""))
        return "\n".join(lines)


class Probe:
    """The host's end of the link, with what the rules need to drive and watch a controller.

    Parameters
    ----------
    transport : Transport
        An open link to the controller (serial, CAN, a plug-in).
    robot : RobotProfile
        The robot's geometry (``k``, for commands that need a given wheel speed).
    estop_pressed : bool
        The operator pressed the e-stop before the run (enables the ``estop.*`` rules).
    answer_s : float
        How long an answer may take [s] (default :data:`ANSWER_S`); the rules that check
        that nothing answers wait this long too.
    """

    def __init__(self, transport: Transport, robot: RobotProfile,
                 estop_pressed: bool = False, answer_s: float = ANSWER_S) -> None:
        self.tr = transport
        transport.set_role("host")
        self.robot = robot
        self.estop_pressed = estop_pressed
        self.answer_s = float(answer_s)
        self.ack: HelloAck | None = None
        self.can = transport.seq_modulus == 256
        #: The e-stop is latched (pressed before the run and not yet cleared by estop.reset).
        self.estop_latched = estop_pressed
        #: Gaps in the host's own streamed frames beyond their period plus SLIP_S [s].
        self.slips: list[float] = []

    # -- sending -----------------------------------------------------------------------------
    def send(self, msg: Message) -> Message:
        """Send ``msg`` with the next sequence number; return it as sent."""
        return self.tr.send(msg)

    def raw(self, data: Any) -> None:
        """Send raw bytes (serial) or an ``(id, data)`` frame (CAN); skip the rule if the
        transport cannot."""
        try:
            self.tr.send_raw(data)
        except NotImplementedError as err:
            raise RuleSkippedError(str(err)) from None

    def serial_frame(self, mtype: int, body: bytes, seq: int | None = None,
                     version: int = PROTOCOL_VERSION, bad_crc: bool = False) -> bytes:
        """A framed serial frame with any header and body (CRC right unless ``bad_crc``)."""
        seq = self.tr.next_seq if seq is None else seq
        raw = bytes([version & 0xFF, mtype & 0xFF, seq & 0xFF, (seq >> 8) & 0xFF]) + body
        crc = crc16(raw) ^ (0x5A5A if bad_crc else 0)
        return b"\x00" + cobs_encode(raw + crc.to_bytes(2, "little")) + b"\x00"

    def command(self, n_rpm: float, omega_dps: float = 0.0, theta_deg: float = 90.0) -> Command:
        """Send a COMMAND as given (float32 on serial, the DBC's scaling on CAN)."""
        return self.tr.send(self.tr.wire_command(n_rpm, omega_dps, theta_deg)
                            if self.can else Command(n_rpm, omega_dps, theta_deg))

    def in_force(self, sent: Message) -> None:
        """Wait (up to the answer time) for a sample acknowledging ``sent``, so that what
        follows is judged against it; without telemetry, a moment."""
        if self.rate > 0:
            self.telemetry(lambda m: m.ack_seq == sent.seq)
        else:
            self.listen(0.01)

    # -- receiving ---------------------------------------------------------------------------
    def listen(self, duration_s: float, keep: Callable[[], Message | None] | None = None,
               every_s: float = 0.02) -> list[tuple[float, Message]]:
        """Everything received for ``duration_s`` [s], with its host time; ``keep()`` is sent
        every ``every_s`` [s] meanwhile (a command stream, heartbeats)."""
        out: list[tuple[float, Message]] = []
        end = time.monotonic() + duration_s
        next_send = time.monotonic()
        last: list[float] = []
        while (now := time.monotonic()) < end:
            if keep is not None and now >= next_send:
                self._keep_send(keep, every_s, last)
                next_send += every_s
            wait = end - now if keep is None else min(end - now, max(0.0, next_send - now))
            msg = self.tr.recv(wait)
            if msg is not None:
                out.append((time.monotonic(), msg))
        return out

    def wait(self, predicate: Callable[[Message], bool], timeout_s: float | None = None,
             keep: Callable[[], Message | None] | None = None, every_s: float = 0.02
             ) -> Message | None:
        """The first message for which ``predicate`` holds within ``timeout_s`` [s] (default:
        the answer time)."""
        end = time.monotonic() + (self.answer_s if timeout_s is None else timeout_s)
        next_send = time.monotonic()
        last: list[float] = []
        while (now := time.monotonic()) < end:
            if keep is not None and now >= next_send:
                self._keep_send(keep, every_s, last)
                next_send += every_s
            wait = end - now if keep is None else min(end - now, max(0.0, next_send - now))
            msg = self.tr.recv(wait)
            if msg is not None and predicate(msg):
                return msg
        return None

    def _keep_send(self, keep: Callable[[], Any], every_s: float, last: list[float]) -> None:
        """Send what ``keep()`` gives (a message, raw bytes or a raw CAN frame); a gap since
        the previous one beyond ``every_s`` + :data:`SLIP_S` is a slip of the host's timing."""
        now = time.monotonic()
        if last and now - last[0] > every_s + SLIP_S:
            self.slips.append(now - last[0])
        last[:] = [now]
        msg = keep()
        if isinstance(msg, bytes | tuple):
            self.raw(msg)
        elif msg is not None:
            self.tr.send(msg)

    def error_then(self, after_s: float = ANSWER_S
                   ) -> tuple[list[tuple[float, Message]], float | None]:
        """Everything received until an ERROR comes (within the answer time) and for
        ``after_s`` [s] after it (what the controller does once it has refused a frame), with
        host times; and the ERROR's arrival time (None when none came: then everything of the
        answer time)."""
        out: list[tuple[float, Message]] = []
        end = time.monotonic() + self.answer_s
        error_at: float | None = None
        while (now := time.monotonic()) < end:
            msg = self.tr.recv(end - now)
            if msg is None:
                continue
            at = time.monotonic()
            out.append((at, msg))
            if error_at is None and isinstance(msg, ErrorMsg):
                error_at = at
                end = at + after_s
        return out, error_at

    def telemetry(self, predicate: Callable[[Telemetry], bool] = lambda m: True,
                  timeout_s: float | None = None, **kw) -> Telemetry | None:
        """The first telemetry sample for which ``predicate`` holds."""
        return self.wait(lambda m: isinstance(m, Telemetry) and predicate(m), timeout_s, **kw)

    def drain(self, duration_s: float = 0.0) -> list[Message]:
        """Read what is there (for ``duration_s`` [s])."""
        return [m for _, m in self.listen(duration_s)]

    # -- sessions ----------------------------------------------------------------------------
    def hello(self) -> HelloAck:
        """Start a session: HELLO (seq 0), repeated every 100 ms, until HELLO_ACK."""
        end = time.monotonic() + 2.0
        hellos = 0
        while time.monotonic() < end:
            self.tr.restart_sequences()
            self.send(Hello(PROTOCOL_VERSION))
            hellos += 1
            ack = self.wait(lambda m: isinstance(m, HelloAck | ErrorMsg), 0.1)
            if isinstance(ack, ErrorMsg):
                raise RuleFailedError(f"HELLO refused with ERROR {ack.code} ({ack.text!r})")
            if isinstance(ack, HelloAck):
                if ack.version != PROTOCOL_VERSION:
                    raise RuleFailedError(f"HELLO_ACK of version {ack.version}")
                # after repeated HELLOs, the answers to the later ones restart the controller
                # again: wait for them, as record does, before driving it
                while hellos > 1:
                    late = self.wait(lambda m: isinstance(m, HelloAck), 0.15)
                    if late is None:
                        break
                    ack = late
                self.tr.expect_next(ack.seq + 1)
                self.ack = ack
                return ack
        raise RuleFailedError("no HELLO_ACK within 2 s")

    @property
    def limit(self) -> float:
        """The announced wheel speed limit [rpm]."""
        assert self.ack is not None
        return float(self.ack.wheel_limit_rpm)

    @property
    def rate(self) -> float:
        """The announced telemetry rate [Hz]."""
        assert self.ack is not None
        return float(self.ack.telemetry_rate_hz)

    def needs_telemetry(self) -> None:
        """Fail: without telemetry what the controller does cannot be seen."""
        if self.rate <= 0:
            raise RuleFailedError("the controller announced no telemetry (0 Hz): what this "
                                  "rule checks cannot be seen")

    def needs_motion(self) -> None:
        """Skip while the e-stop is latched: the wheels cannot turn."""
        if self.estop_latched:
            raise RuleSkippedError("the e-stop is latched (estop.reset could not clear it: the "
                                   "button is held): the wheels cannot turn")

    def end(self) -> None:
        """STOP, then let the wheels settle (best effort)."""
        try:
            self.send(Stop())
            self.listen(0.05)
        except Exception:  # the next rule starts with its own HELLO anyway
            pass

    def moving(self, n_rpm: float) -> Callable[[], Message]:
        """A ``keep`` that streams one command at 50 Hz."""
        return lambda: self.tr.wire_command(n_rpm, 0.0, 90.0)

    def errors(self, msgs: Sequence[Message]) -> list[ErrorMsg]:
        return [m for m in msgs if isinstance(m, ErrorMsg)]


def _fail_if(condition: bool, text: str) -> None:
    if condition:
        raise RuleFailedError(text)


def _peak(n: float, omega: float, theta: float, k: float) -> float:
    return float(max(abs(w) for w in command_to_wheels(n, omega, theta, k)))


# -- the rules -----------------------------------------------------------------------------
def rule_hello_answer(p: Probe) -> str:
    ack = p.hello()
    _fail_if(ack.seq != 0, f"HELLO_ACK seq {ack.seq}, must be 0")
    _fail_if(ack.watchdog_ms != int(WATCHDOG_S * 1000),
             f"watchdog {ack.watchdog_ms} ms announced, the protocol's is 250 ms")
    _fail_if(not (math.isfinite(ack.wheel_limit_rpm) and ack.wheel_limit_rpm > 0),
             f"wheel speed limit {ack.wheel_limit_rpm!r} rpm announced")
    return (f"version {ack.version}, {ack.telemetry_rate_hz} Hz, watchdog {ack.watchdog_ms} ms, "
            f"limit {ack.wheel_limit_rpm:g} rpm")


def rule_hello_restart(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    period_us = 1e6 / p.rate
    first = p.telemetry(timeout_s=p.answer_s + 2.0 / p.rate)
    _fail_if(first is None, "no telemetry after HELLO_ACK")
    _fail_if(first.seq != 1, f"first telemetry after HELLO_ACK has seq {first.seq}, must be 1")
    _fail_if(first.time_us > period_us + 2000, f"first telemetry at time_us {first.time_us}: "
             "the clock did not restart at HELLO")
    _fail_if(first.ack_seq != 0, f"ack_seq {first.ack_seq} after HELLO, must be 0")
    _fail_if(not first.status & Status.STOPPED, "STOPPED not set after HELLO")
    _fail_if(bool(first.status & Status.WATCHDOG), "WATCHDOG set right after HELLO")
    # a second session: no stale ack_seq, clock and numbering restart again
    for _ in range(5):
        p.send(Heartbeat())
    p.listen(0.3, keep=lambda: Heartbeat(), every_s=0.05)
    p.hello()
    again = p.telemetry(timeout_s=p.answer_s + 2.0 / p.rate)
    _fail_if(again is None, "no telemetry after the second HELLO")
    _fail_if(again.ack_seq != 0, f"ack_seq {again.ack_seq} after a second HELLO (stale): must "
             "be 0")
    _fail_if(again.seq != 1 or again.time_us > period_us + 2000,
             f"second HELLO: telemetry seq {again.seq} at {again.time_us} us, must restart")
    return "clock, seq and ack_seq restart at every HELLO; STOPPED set"


def rule_hello_version(p: Probe) -> str:
    p.hello()
    p.listen(0.1)
    seen = []
    for version in (PROTOCOL_VERSION - 1, PROTOCOL_VERSION + 1):
        p.tr.restart_sequences()
        p.send(Hello(version))
        msgs = [m for _, m in p.error_then()[0]]
        errs = p.errors(msgs)
        _fail_if(any(isinstance(m, HelloAck) for m in msgs),
                 f"HELLO of version {version} answered with HELLO_ACK")
        _fail_if(not errs or errs[0].code != ErrorCode.VERSION_MISMATCH,
                 f"HELLO of version {version}: no ERROR {int(ErrorCode.VERSION_MISMATCH)} "
                 f"(got {[e.code for e in errs]})")
        seen.append(version)
        times = [m.time_us for m in msgs if isinstance(m, Telemetry)]
        _fail_if(p.rate > 0 and any(b < a for a, b in itertools.pairwise(times)),
                 f"the HELLO of version {version} restarted the session")
    return f"versions {seen} refused with ERROR 1, session kept"


def rule_hello_body(p: Probe) -> str:
    p.hello()
    p.listen(0.1)
    if p.can:
        p.raw((0x103, bytes([PROTOCOL_VERSION, 0, 0])))
    else:
        p.raw(p.serial_frame(MsgType.HELLO, b"\x01", seq=0))
    msgs = p.drain(p.answer_s)
    _fail_if(any(isinstance(m, HelloAck) for m in msgs), "a HELLO with a body was answered")
    times = [m.time_us for m in msgs if isinstance(m, Telemetry)]
    _fail_if(any(b < a for a, b in itertools.pairwise(times)),
             "a HELLO with a body restarted the session")
    return "dropped, no answer, no restart"


def rule_telemetry_rate(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    p.listen(0.05)
    start = time.monotonic()
    got = [(t, m) for t, m in p.listen(1.0) if isinstance(m, Telemetry)]
    # by the host clock within 30 % (a loaded host reads late); by the controller's exactly
    expected = p.rate * (time.monotonic() - start)
    _fail_if(abs(len(got) - expected) > max(2.0, 0.3 * expected),
             f"{len(got)} samples in 1 s, {p.rate:g} Hz announced")
    steps = [(b.time_us - a.time_us) % (1 << 32) for (_, a), (_, b) in itertools.pairwise(got)]
    period = 1e6 / p.rate
    off = [s for s in steps if abs(s - period) > max(0.02 * period, 1000)]
    _fail_if(len(off) > max(1, len(steps) // 20),
             f"time_us steps {sorted(set(off))[:5]} us, the period is {period:.0f} us")
    m = p.tr.seq_modulus
    gaps = [(b.seq - a.seq) % m for (_, a), (_, b) in itertools.pairwise(got)]
    _fail_if(any(g == 0 or g >= m // 2 for g in gaps), "telemetry seq went back")
    reserved = [mm.status for _, mm in got if mm.status & ~STATUS_DEFINED]
    if reserved:
        raise RuleFailedError(f"reserved status bits set: {reserved[0]:#06x}")
    return f"{len(got)} samples in 1 s at {p.rate:g} Hz announced, steps {period:.0f} us"


def rule_ping(p: Probe) -> str:
    p.hello()
    fed = p.send(Heartbeat())
    if p.rate > 0:
        _fail_if(p.telemetry(lambda m: m.ack_seq == fed.seq) is None,
                 "HEARTBEAT not acknowledged")
    token = random.Random().getrandbits(32)
    p.send(Ping(token))
    pong = p.wait(lambda m: isinstance(m, Pong))
    _fail_if(pong is None, "no PONG")
    _fail_if(pong.token != token, f"PONG token {pong.token}, PING's {token}")
    if p.rate > 0:
        tlm = p.telemetry(timeout_s=p.answer_s)
        _fail_if(tlm is not None and tlm.ack_seq != fed.seq, "PING moved ack_seq")
    return "PONG with the token; ack_seq unchanged"


def _accepts(p: Probe, sent: Command, what: str) -> Telemetry:
    tlm = p.telemetry(lambda m: m.ack_seq == sent.seq, timeout_s=p.answer_s)
    errs = [m for m in p.drain(0.0) if isinstance(m, ErrorMsg)]
    _fail_if(tlm is None, f"{what}: never acknowledged (ack_seq {sent.seq})")
    _fail_if(bool(errs), f"{what}: ERROR {errs[0].code if errs else ''}")
    return tlm


def rule_command_valid(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    p.needs_motion()
    target = 0.25 * p.limit
    sent = p.command(target)
    tlm = _accepts(p, sent, f"n = {target:g}")
    _fail_if(bool(tlm.status & Status.STOPPED), "STOPPED still set after a valid COMMAND")
    later = p.listen(0.5, keep=p.moving(target))
    wheels = [m.wheel_rpm for _, m in later if isinstance(m, Telemetry)]
    _fail_if(not wheels or min(wheels[-1]) < 0.5 * target,
             f"wheels at {wheels[-1] if wheels else None} rpm 0.5 s after n = {target:g} rpm")
    at_limit = p.command(p.limit)
    _accepts(p, at_limit, f"n = {p.limit:g} (the limit)")
    p.end()
    return f"n = {target:g} rpm reached {min(wheels[-1]):.1f} rpm; n at the limit accepted"


def _refused(p: Probe, send: Callable[[], Any], what: str, base: Command) -> None:
    sent = send()
    # the ERROR within the answer time, then ANSWER_S (two telemetry periods at least) of what
    # the controller does after it: its samples must not acknowledge the refused command, nor
    # drive beyond the limit
    after_s = max(ANSWER_S, 2.0 / p.rate) if p.rate > 0 else ANSWER_S
    msgs, error_at = p.error_then(after_s)
    errs = p.errors([m for _, m in msgs])
    _fail_if(not errs, f"{what}: no ERROR 2")
    _fail_if(errs[0].code != ErrorCode.BAD_COMMAND, f"{what}: ERROR {errs[0].code}, must be 2")
    seq = getattr(sent, "seq", None)
    for _, m in msgs:
        if isinstance(m, Telemetry):
            _fail_if(seq is not None and m.ack_seq == seq, f"{what}: acknowledged (ack_seq)")
            _fail_if(max(abs(w) for w in m.wheel_rpm) > p.limit * 1.02,
                     f"{what}: a wheel at {max(abs(w) for w in m.wheel_rpm):.1f} rpm")
    if p.rate > 0:
        after = [m for at, m in msgs if isinstance(m, Telemetry) and at >= error_at]
        _fail_if(not after, f"{what}: no telemetry in the {after_s:g} s after the ERROR "
                 f"(announced {p.rate:g} Hz)")
        _fail_if(after[-1].ack_seq != base.seq,
                 f"{what}: ack_seq moved from {base.seq} to {after[-1].ack_seq}")


def rule_command_non_finite(p: Probe) -> str:
    if p.can:
        raise RuleSkippedError("CAN signals are integers: they carry no NaN or infinity")
    p.hello()
    base = p.command(0.1 * p.limit)
    p.listen(0.05)
    cases = 0
    for field_ in range(3):
        for bad in (math.nan, math.inf, -math.inf):
            values = [0.1 * p.limit, 0.0, 90.0]
            values[field_] = bad
            base = p.send(Command(0.1 * p.limit, 0.0, 90.0))
            p.in_force(base)
            _refused(p, lambda v=tuple(values): p.send(Command(*v)),
                     f"{('n', 'omega', 'theta')[field_]} = {bad}", base)
            cases += 1
    p.end()
    return f"{cases} commands with NaN/inf refused with ERROR 2 and ignored"


def rule_command_beyond_limit(p: Probe) -> str:
    p.hello()
    k = p.robot.k
    lim = p.limit
    cases = [(1.01 * lim, 0.0, 90.0), (-1.01 * lim, 0.0, 270.0),
             (0.0, 1.01 * lim * 6.0 / k, 90.0), (0.8 * lim, 0.5 * lim * 6.0 / k, 45.0)]
    if not p.can:
        cases += [(5000.0, 0.0, 90.0), (1e30, 0.0, 90.0), (3.4e38, 0.0, 90.0),
                  (0.0, 0.0, 700.0)]
    done = 0
    for n, w, th in cases:
        if p.can and max(abs(n), abs(w)) > 327.67:
            continue
        if _peak(n, w, th, k) <= lim * 1.000001 and abs(th) <= 655.36:
            continue
        base = p.command(0.1 * lim)
        p.in_force(base)
        _refused(p, lambda c=(n, w, th): p.command(*c), f"({n:g}, {w:g}, {th:g})", base)
        done += 1
    p.end()
    _fail_if(done == 0, "no command beyond the limit could be carried")
    return f"{done} commands beyond the {lim:g} rpm limit refused with ERROR 2, ignored"


def rule_command_k(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    k, lim = p.robot.k, p.limit
    near, beyond = 0.99 * lim * 6.0 / k, 1.01 * lim * 6.0 / k  # pure rotations [deg/s]
    if p.can and beyond > 327.67:
        raise RuleSkippedError(f"a rotation of {beyond:.1f} deg/s does not fit the CAN signal")
    base = p.command(0.1 * lim)
    p.in_force(base)
    try:
        _accepts(p, p.command(0.0, near, 90.0), f"omega = {near:.2f} deg/s")
    except RuleFailedError as err:
        raise RuleFailedError(f"{err}: it needs {0.99 * lim:.2f} rpm by k = {k:.6g} (--robot), "
                              "so the controller's k is more than 1 % larger") from None
    base = p.command(0.1 * lim)
    p.in_force(base)
    try:
        _refused(p, lambda: p.command(0.0, beyond, 90.0), f"omega = {beyond:.2f} deg/s", base)
    except RuleFailedError as err:
        raise RuleFailedError(f"{err}: it needs {1.01 * lim:.2f} rpm by k = {k:.6g} (--robot), "
                              "so the controller's k is more than 1 % smaller") from None
    p.end()
    return (f"rotations needing 0.99 and 1.01 x {lim:g} rpm by k = {k:.6g} accepted and "
            "refused: the controller's k is the host's within 1 %")


def rule_command_malformed(p: Probe) -> str:
    p.hello()
    base = p.command(0.1 * p.limit)
    p.listen(0.02)
    if p.can:
        bad: Any = (0x101, _can_command(p, 0.2 * p.limit)[:7])
        what = "MH_COMMAND of 7 bytes"
    else:
        body = Command(0.2 * p.limit, 0.0, 90.0)
        bad = p.serial_frame(MsgType.COMMAND, pack_frame(body)[4:-2][:8], seq=p.tr.next_seq)
        what = "COMMAND with an 8-byte body"
    _refused(p, lambda: p.raw(bad), what, base)
    if p.can:
        base = p.command(0.1 * p.limit)
        p.listen(0.02)
        frame = _can_command(p, 0.2 * p.limit)[:7] + b"\x01"
        _refused(p, lambda: p.raw((0x101, frame)), "MH_COMMAND with reserved = 1", base)
        what += " and one with reserved != 0"
    p.end()
    return f"{what} refused with ERROR 2"


def _can_command(p: Probe, n_rpm: float) -> bytes:
    from .can_link import CanCodec

    ((_, data),) = CanCodec().encode(Command(n_rpm, 0.0, 90.0, p.tr.next_seq))
    return data


def rule_frame_damaged(p: Probe) -> str:
    p.hello()
    base = p.command(0.1 * p.limit)
    p.listen(0.02)
    if p.can:
        p.raw((0x170, b"\x01\x02"))  # an id the database does not know
        what = "unknown id"
    else:
        cmd = pack_frame(Command(0.3 * p.limit, 0.0, 90.0))[4:-2]
        rng = random.Random(1)
        p.raw(bytes(rng.getrandbits(8) for _ in range(200)))
        p.raw(b"\x00" + bytes(rng.randrange(1, 256) for _ in range(120)) + b"\x00")
        p.raw(p.serial_frame(MsgType.COMMAND, cmd, bad_crc=True))
        p.raw(p.serial_frame(0x7E, b"\x01\x02"))
        p.raw(p.serial_frame(MsgType.COMMAND, cmd, version=PROTOCOL_VERSION - 1))
        what = "garbage, an oversize frame, a bad CRC, an unknown type, a wrong version"
    msgs = p.drain(p.answer_s)
    errs = p.errors(msgs)
    if errs:
        raise RuleFailedError(f"answered damaged frames with ERROR {errs[0].code}")
    for m in msgs:
        if isinstance(m, Telemetry):
            _fail_if(m.ack_seq != base.seq, f"a damaged frame was acknowledged (ack_seq "
                     f"{m.ack_seq})")
    token = 12345
    p.send(Ping(token))
    pong = p.wait(lambda m: isinstance(m, Pong) and m.token == token)
    _fail_if(pong is None, "no PONG after the damaged frames: not resynchronised")
    p.end()
    return f"{what}: ignored, no answer, resynchronised"


def rule_stop(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    p.needs_motion()
    target = 0.25 * p.limit
    p.listen(0.4, keep=p.moving(target))
    stop = p.send(Stop())
    tlm = p.telemetry(lambda m: m.ack_seq == stop.seq)
    _fail_if(tlm is None, "STOP never acknowledged")
    _fail_if(not tlm.status & Status.STOPPED, "STOPPED not set after STOP")
    last = p.telemetry(lambda m: m.time_us >= tlm.time_us + 800_000, timeout_s=1.5,
                       keep=lambda: Heartbeat(), every_s=0.08)
    _fail_if(last is None, "telemetry stopped after STOP")
    _fail_if(max(abs(w) for w in last.wheel_rpm) > 0.05 * target,
             f"wheels at {last.wheel_rpm} 0.8 s after STOP")
    _fail_if(not last.status & Status.STOPPED, "STOPPED cleared without a COMMAND")
    sent = p.command(0.1 * p.limit)
    after = p.telemetry(lambda m: m.ack_seq == sent.seq)
    _fail_if(after is None or bool(after.status & Status.STOPPED),
             "a COMMAND after STOP did not clear STOPPED")
    p.end()
    return "wheels stopped, STOPPED until the next COMMAND"


def _watchdog_trip(p: Probe, target: float) -> tuple[Telemetry, Telemetry]:
    p.listen(0.3, keep=p.moving(target))
    last = p.command(target)
    acked = p.telemetry(lambda m: m.ack_seq == last.seq)
    _fail_if(acked is None, "COMMAND not acknowledged")
    tripped = p.telemetry(lambda m: bool(m.status & Status.WATCHDOG), timeout_s=0.6)
    _fail_if(tripped is None, "no WATCHDOG within 0.6 s of the last COMMAND")
    return acked, tripped


def rule_watchdog_fires(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    acked, tripped = _watchdog_trip(p, 0.25 * p.limit)
    dt_ms = ((tripped.time_us - acked.time_us) % (1 << 32)) / 1000
    period_ms = 1000 / p.rate
    _fail_if(not 250 - period_ms - 30 <= dt_ms <= 250 + period_ms + 60,
             f"WATCHDOG {dt_ms:.0f} ms after the last COMMAND, must be 250 ms")
    later = p.telemetry(lambda m: m.time_us >= tripped.time_us + 800_000, timeout_s=1.5)
    _fail_if(later is None or max(abs(w) for w in later.wheel_rpm) > 0.05 * p.limit,
             f"wheels at {later.wheel_rpm if later else None} 0.8 s after the watchdog")
    return f"WATCHDOG {dt_ms:.0f} ms after the last COMMAND, wheels stopped"


def rule_watchdog_fed(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    p.needs_motion()
    target = 0.25 * p.limit
    p.listen(0.3, keep=p.moving(target))
    msgs = p.listen(0.6, keep=lambda: Heartbeat(), every_s=0.08)
    tlm = [m for _, m in msgs if isinstance(m, Telemetry)]
    _fail_if(any(m.status & Status.WATCHDOG for m in tlm),
             "WATCHDOG set although HEARTBEAT came every 80 ms")
    _fail_if(not tlm or min(tlm[-1].wheel_rpm) < 0.5 * target,
             "the command in force was not held under HEARTBEATs")
    p.end()
    return "HEARTBEAT every 80 ms holds the command for 0.6 s"


def rule_watchdog_latched(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    _watchdog_trip(p, 0.25 * p.limit)
    hb = p.send(Heartbeat())
    fed = p.telemetry(lambda m: m.ack_seq == hb.seq)
    _fail_if(fed is None, "HEARTBEAT not acknowledged")
    _fail_if(not fed.status & Status.WATCHDOG, "a HEARTBEAT cleared WATCHDOG")
    msgs = p.listen(0.3, keep=lambda: Heartbeat(), every_s=0.08)
    tlm = [m for _, m in msgs if isinstance(m, Telemetry)]
    _fail_if(not tlm or not all(m.status & Status.WATCHDOG for m in tlm),
             "WATCHDOG cleared without a COMMAND")
    sent = p.command(0.1 * p.limit)
    after = p.telemetry(lambda m: m.ack_seq == sent.seq)
    _fail_if(after is None or bool(after.status & Status.WATCHDOG),
             "a COMMAND did not clear WATCHDOG")
    p.end()
    return "WATCHDOG stays under HEARTBEATs, cleared by the next COMMAND"


def rule_watchdog_refused(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    target = 0.25 * p.limit
    p.listen(0.3, keep=p.moving(target))
    if p.can:
        if 1.01 * p.limit > 327.67:
            raise RuleSkippedError("no refused command fits the CAN signals for this limit")
        bad = p.tr.wire_command(1.01 * p.limit, 0.0, 90.0)
    else:
        bad = Command(math.nan, 0.0, 90.0)
    tripped = p.telemetry(lambda m: bool(m.status & Status.WATCHDOG), timeout_s=0.7,
                          keep=lambda: bad, every_s=0.02)
    _fail_if(tripped is None, "refused commands fed the watchdog")
    p.end()
    return "refused commands do not feed the watchdog"


def _trip_at_250_ms(p: Probe, acked: Telemetry, tripped: Telemetry | None, what: str) -> float:
    """The watchdog tripped 250 ms (within a period and the link's jitter) after ``acked``."""
    _fail_if(tripped is None, f"no WATCHDOG within 0.7 s: {what} fed the watchdog")
    dt_ms = ((tripped.time_us - acked.time_us) % (1 << 32)) / 1000
    period_ms = 1000 / p.rate
    _fail_if(dt_ms > 250 + period_ms + 60,
             f"WATCHDOG {dt_ms:.0f} ms after the last valid frame, with {what} meanwhile: "
             "they fed it")
    return dt_ms


def _not_fed_by(p: Probe, feed: Callable[[], Any], what: str) -> str:
    """A command in force, then only ``feed()`` every 50 ms: the watchdog trips at 250 ms."""
    p.hello()
    p.needs_telemetry()
    target = 0.25 * p.limit
    p.listen(0.2, keep=p.moving(target))
    last = p.command(target)
    acked = p.telemetry(lambda m: m.ack_seq == last.seq)
    _fail_if(acked is None, "COMMAND not acknowledged")
    tripped = p.telemetry(lambda m: bool(m.status & Status.WATCHDOG), timeout_s=0.7,
                          keep=feed, every_s=0.05)
    dt_ms = _trip_at_250_ms(p, acked, tripped, what)
    p.end()
    return f"WATCHDOG {dt_ms:.0f} ms after the last COMMAND, {what} every 50 ms meanwhile"


def rule_watchdog_ping(p: Probe) -> str:
    token = itertools.count(1)
    return _not_fed_by(p, lambda: Ping(next(token)), "PINGs")


def rule_watchdog_damaged(p: Probe) -> str:
    if p.can:
        frames = itertools.cycle([(0x170, b"\x01\x02"), (0x101, b"\x01\x02\x03")])
        return _not_fed_by(p, lambda: next(frames), "frames of unknown id or wrong length")
    cmd = pack_frame(Command(0.25 * p.limit, 0.0, 90.0))[4:-2]
    rng = random.Random(2)

    def damaged() -> bytes:
        return (bytes(rng.randrange(1, 256) for _ in range(8))
                + p.serial_frame(MsgType.COMMAND, cmd, bad_crc=True)
                + p.serial_frame(0x7E, b"\x01")
                + p.serial_frame(MsgType.HEARTBEAT, b"", version=PROTOCOL_VERSION - 1))

    return _not_fed_by(p, damaged, "garbage bytes and damaged frames")


def rule_watchdog_idle(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    first = p.telemetry(timeout_s=p.answer_s + 2.0 / p.rate)
    _fail_if(first is None, "no telemetry after HELLO_ACK")
    tripped = p.telemetry(lambda m: bool(m.status & Status.WATCHDOG), timeout_s=0.7)
    _fail_if(tripped is None, "no WATCHDOG 0.7 s after a HELLO with nothing after it: the "
             "watchdog does not run while nothing is in force")
    _fail_if(tripped.time_us > 250_000 + 1e6 / p.rate + 60_000,
             f"WATCHDOG at {tripped.time_us / 1000:.0f} ms after the HELLO, must be 250 ms")
    sent = p.command(0.1 * p.limit)
    _fail_if(p.telemetry(lambda m: m.ack_seq == sent.seq) is None, "COMMAND not acknowledged")
    stop = p.send(Stop())
    stopped = p.telemetry(lambda m: m.ack_seq == stop.seq)
    _fail_if(stopped is None, "STOP not acknowledged")
    again = p.telemetry(lambda m: bool(m.status & Status.WATCHDOG), timeout_s=0.7)
    dt_ms = _trip_at_250_ms(p, stopped, again, "nothing after a STOP (the watchdog did not run)")
    return f"WATCHDOG 250 ms after a HELLO and {dt_ms:.0f} ms after a STOP, nothing in force"


def rule_watchdog_estop_error(p: Probe) -> str:
    if not p.estop_latched:
        raise RuleSkippedError("needs the e-stop pressed and held through the run "
                               "(--estop-pressed, the button not released)")
    p.hello()
    p.needs_telemetry()
    msgs = p.listen(0.7, keep=lambda: EstopReset(), every_s=0.05)
    codes = {m.code for _, m in msgs if isinstance(m, ErrorMsg)}
    tlm = [m for _, m in msgs if isinstance(m, Telemetry)]
    if any(not m.status & Status.ESTOP for m in tlm):
        p.estop_latched = False
        raise RuleSkippedError("the e-stop button was released: ESTOP_RESET was taken")
    _fail_if(codes != {int(ErrorCode.ESTOP_HELD)},
             f"ESTOP_RESET with the button held answered with ERROR {sorted(codes)}, must be 3")
    tripped = next((m for m in tlm if m.status & Status.WATCHDOG), None)
    _fail_if(tripped is None, "no WATCHDOG in 0.7 s of ESTOP_RESETs answered with ERROR 3: "
             "they fed the watchdog")
    _fail_if(tripped.time_us > 250_000 + 1e6 / p.rate + 60_000,
             f"WATCHDOG at {tripped.time_us / 1000:.0f} ms after the HELLO, ESTOP_RESETs "
             "answered with ERROR 3 every 50 ms: they fed it")
    return "ESTOP_RESETs answered with ERROR 3 do not feed the watchdog"


def rule_seq_wrap(p: Probe) -> str:
    p.hello()
    p.needs_telemetry()
    m = p.tr.seq_modulus
    p.tr.set_next_seq(m - 3)
    seen = []
    for _ in range(6):
        sent = p.command(0.1 * p.limit)
        tlm = p.telemetry(lambda x, s=sent.seq: x.ack_seq == s)
        _fail_if(tlm is None, f"COMMAND with seq {sent.seq} not acknowledged")
        seen.append(sent.seq)
    p.end()
    return f"host seq {seen} acknowledged across the wrap"


def rule_estop_harmless(p: Probe) -> str:
    if p.estop_latched:
        raise RuleSkippedError("the e-stop is latched (see estop.*)")
    p.hello()
    p.needs_telemetry()
    reset = p.send(EstopReset())
    tlm = p.telemetry(lambda m: m.ack_seq == reset.seq)
    _fail_if(tlm is None, "ESTOP_RESET not acknowledged")
    msgs = p.drain(0.2)
    _fail_if(bool(p.errors(msgs)), "ESTOP_RESET without an e-stop answered with an ERROR")
    _fail_if(bool(tlm.status & Status.ESTOP) or not tlm.status & Status.STOPPED,
             f"status {tlm.status:#06x} after ESTOP_RESET without an e-stop")
    return "acknowledged, nothing changed"


def rule_estop_held(p: Probe) -> str:
    if not p.estop_pressed:
        raise RuleSkippedError("needs the e-stop pressed before the run (--estop-pressed)")
    p.hello()
    p.needs_telemetry()
    first = p.telemetry(timeout_s=0.5)
    _fail_if(first is None or not first.status & Status.ESTOP,
             "ESTOP not set after HELLO: the HELLO cleared the e-stop (or it is not pressed)")
    msgs = p.listen(0.4, keep=p.moving(0.25 * p.limit))
    tlm = [m for _, m in msgs if isinstance(m, Telemetry)]
    _fail_if(not all(m.status & Status.ESTOP for m in tlm), "a COMMAND cleared ESTOP")
    _fail_if(max(abs(w) for m in tlm for w in m.wheel_rpm) > 0.02 * p.limit,
             "wheels moved with the e-stop latched")
    p.hello()
    again = p.telemetry(timeout_s=0.5)
    _fail_if(again is None or not again.status & Status.ESTOP, "a HELLO cleared the e-stop")
    return "ESTOP held through COMMANDs and a HELLO, wheels at zero"


def rule_estop_reset(p: Probe) -> str:
    if not p.estop_pressed:
        raise RuleSkippedError("needs the e-stop pressed before the run (--estop-pressed)")
    p.hello()
    p.needs_telemetry()
    reset = p.send(EstopReset())
    # ERROR 3 comes at once, before the next telemetry, and an ESTOP_RESET it answers is not
    # acknowledged: wait for either, or the ERROR would be read past and the rule fail
    answer = p.wait(lambda m: isinstance(m, ErrorMsg)
                    or (isinstance(m, Telemetry) and m.ack_seq == reset.seq))
    errs = [answer] if isinstance(answer, ErrorMsg) else p.errors(p.drain(0.05))
    if errs and errs[0].code == ErrorCode.ESTOP_HELD:
        raise RuleSkippedError("the e-stop button is still pressed (ERROR 3): release it first")
    if errs:
        raise RuleFailedError(f"ESTOP_RESET answered with ERROR {errs[0].code}")
    _fail_if(answer is None, "ESTOP_RESET not acknowledged")
    later = p.telemetry(lambda m: not m.status & Status.ESTOP, timeout_s=0.3)
    _fail_if(later is None, "ESTOP_RESET did not clear ESTOP")
    p.estop_latched = False  # the motion rules that follow can run
    _fail_if(not later.status & Status.STOPPED, "no STOPPED after ESTOP_RESET")
    sent = p.command(0.1 * p.limit)
    moving = p.telemetry(lambda m: m.ack_seq == sent.seq and not m.status & Status.STOPPED)
    _fail_if(moving is None, "a COMMAND after ESTOP_RESET was not taken")
    p.end()
    return "cleared by ESTOP_RESET only; STOPPED until the next COMMAND"


def rule_robust_flood(p: Probe) -> str:
    p.hello()
    n = 500 if p.can else 2500
    start = time.monotonic()
    for _ in range(n):
        for _attempt in range(200):
            try:
                p.command(0.1 * p.limit)
                break
            except LinkError:  # our own output buffer is full: let the controller read
                p.tr.recv(0.002)
        p.tr.recv(0.0)
    sent_s = time.monotonic() - start
    token = 777
    p.send(Ping(token))
    pong = p.wait(lambda m: isinstance(m, Pong) and m.token == token, timeout_s=2.0)
    _fail_if(pong is None, f"no PONG after a flood of {n} commands")
    if p.rate > 0:
        got = [m for _, m in p.listen(0.5, keep=p.moving(0.1 * p.limit))
               if isinstance(m, Telemetry)]
        _fail_if(len(got) < 0.4 * p.rate * 0.5, f"{len(got)} telemetry samples in 0.5 s after "
                 "the flood")
    p.end()
    return f"{n} commands in {sent_s:.2f} s ({n / max(sent_s, 1e-9):.0f}/s), still answering"


#: Every rule by name, in the order they run (the e-stop ones last: they leave it cleared;
#: with the e-stop pressed, :data:`ESTOP_FIRST` run first): what it checks, and the section
#: and sentence of ``drivers/protocol.md`` it checks.
RULES: dict[str, tuple[Callable[[Probe], str], str, str]] = {
    "hello.answer": (rule_hello_answer, "HELLO is answered with HELLO_ACK (seq 0, version, "
                     "rate, 250 ms, a wheel speed limit)",
                     'HELLO / version exchange: "answers HELLO_ACK with `seq` 0"'),
    "hello.restart": (rule_hello_restart, "every HELLO restarts clock, seq and ack_seq; "
                      "STOPPED set", 'HELLO / version exchange: "Every HELLO is answered this '
                      'way"'),
    "hello.version": (rule_hello_version, "a HELLO of another version gets ERROR 1, the "
                      "session goes on", 'HELLO / version exchange: "A HELLO of another '
                      'version is answered with ERROR code 1"'),
    "hello.body": (rule_hello_body, "a HELLO with a body is dropped (no answer, no restart)",
                   'HELLO / version exchange: "A HELLO with a non-empty body is malformed"'),
    "telemetry.rate": (rule_telemetry_rate, "telemetry at the announced rate, time_us on the "
                       "period, seq increasing, reserved status bits 0",
                       'Telemetry: "each sample carries the time it was taken, on the '
                       'announced period"'),
    "ping": (rule_ping, "PING is answered with PONG carrying its token",
             'PING: "answered at once with a PONG carrying the same token"'),
    "command.valid": (rule_command_valid, "a valid COMMAND (also at the limit) is acknowledged "
                      "and clears STOPPED", 'COMMAND: "A valid COMMAND is in force from its '
                      'arrival"'),
    "command.non_finite": (rule_command_non_finite, "NaN/inf in any field: ERROR 2, ignored",
                           'COMMAND: "a field is not finite"'),
    "command.beyond_limit": (rule_command_beyond_limit, "a wheel target beyond the announced "
                             "limit or |theta| > 655.36: ERROR 2, ignored",
                             'COMMAND: "exceeds `wheel_limit_rpm` by more than 1 ppm"'),
    "command.k": (rule_command_k, "the controller's k is the host's (--robot) within 1 %: a "
                  "rotation needing 0.99 x the limit accepted, 1.01 x refused",
                  'COMMAND: "`k` is not on the wire"'),
    "command.malformed": (rule_command_malformed, "a COMMAND of the wrong length (CAN: or "
                          "reserved != 0): ERROR 2, ignored",
                          'COMMAND: "on serial, the body is not 12 bytes"'),
    "frame.damaged": (rule_frame_damaged, "garbage, bad CRC, unknown type, wrong version: "
                      "ignored without answer, resynchronised",
                      'Counters: "A receiver drops a frame that fails"'),
    "stop": (rule_stop, "STOP stops the wheels, STOPPED until the next COMMAND",
             'STOP: "stops the wheels (status `STOPPED`) until the next valid COMMAND"'),
    "watchdog.fires": (rule_watchdog_fires, "250 ms without a valid frame: WATCHDOG, wheels "
                       "stopped", 'Watchdog: "has arrived for **250 ms**"'),
    "watchdog.fed": (rule_watchdog_fed, "HEARTBEAT every 80 ms holds the command",
                     'Watchdog: "a HEARTBEAT feeds the timer"'),
    "watchdog.latched": (rule_watchdog_latched, "WATCHDOG stays under HEARTBEAT until a "
                         "COMMAND", 'Watchdog: "does not release a watchdog stop"'),
    "watchdog.refused": (rule_watchdog_refused, "refused commands do not feed the watchdog",
                         'Watchdog: "refused commands, PINGs and damaged frames do not count"'),
    "watchdog.ping": (rule_watchdog_ping, "PINGs do not feed the watchdog",
                      'Watchdog: "refused commands, PINGs and damaged frames do not count"'),
    "watchdog.damaged": (rule_watchdog_damaged, "garbage bytes and damaged frames do not feed "
                         "the watchdog", 'Watchdog: "refused commands, PINGs and damaged '
                         'frames do not count"'),
    "watchdog.idle": (rule_watchdog_idle, "the watchdog runs with nothing in force (after "
                      "HELLO, after STOP)", 'Watchdog: "The watchdog runs for the whole '
                      'session, whatever is in force"'),
    "watchdog.estop_error": (rule_watchdog_estop_error, "an ESTOP_RESET answered with ERROR 3 "
                             "does not feed the watchdog", 'Watchdog: "An ESTOP_RESET answered '
                             'with ERROR 3 does not feed it"'),
    "seq.wrap": (rule_seq_wrap, "host seq wrapping around is acknowledged",
                 'Sequence numbers: "it wraps with the host\'s `seq`"'),
    "robust.flood": (rule_robust_flood, "a flood of commands: still answering, telemetry "
                     "goes on", 'Robustness: "It keeps its telemetry at the announced rate '
                     'while it is flooded"'),
    "estop.harmless": (rule_estop_harmless, "ESTOP_RESET without an e-stop changes nothing",
                       'E-stop: "ESTOP_RESET without a latched e-stop changes nothing"'),
    "estop.held": (rule_estop_held, "a latched e-stop holds through COMMAND and HELLO",
                   'E-stop: "A HELLO, a STOP or a COMMAND never clears it"'),
    "estop.reset": (rule_estop_reset, "only ESTOP_RESET clears the e-stop; STOPPED after",
                    'E-stop: "Only ESTOP_RESET clears the latch"'),
}

#: With the e-stop pressed before the run these run first, in this order: the e-stop is
#: latched for estop.held, estop.reset clears it when the button is released (the motion rules
#: then run), and watchdog.estop_error needs it still held (ERROR 3).
ESTOP_FIRST = ("estop.held", "estop.reset", "watchdog.estop_error")


def select_rules(patterns: Sequence[str] = ()) -> list[str]:
    """Rule names matching any of ``patterns`` (a name or a prefix such as ``watchdog``)."""
    if not patterns:
        return list(RULES)
    out = [name for name in RULES
           if any(name == pat or name.startswith(pat.rstrip(".") + ".") for pat in patterns)]
    return out


def _run_rules(probe: Probe, rules: Sequence[str], results: list,
               progress: Callable[[RuleResult], None] | None, guard: SignalGuard) -> None:
    """Run the rules in turn, each ended by STOP (also when a signal ends the run in it:
    signals are kept while STOP is sent, and raised after it); a rule whose own timing slipped
    runs again (at most :data:`ATTEMPTS` times); after a lost link the rest are skipped."""
    lost: str | None = None
    names = select_rules(rules)
    if probe.estop_pressed:
        names = [n for n in ESTOP_FIRST if n in names] + [n for n in names
                                                           if n not in ESTOP_FIRST]
    for name in names:
        check, _, section = RULES[name]
        start = time.monotonic()
        if lost is not None:
            results.append(RuleResult(name, "skip", f"not run: {lost}", 0.0, section))
            continue
        slipped: list[float] = []
        attempt, send_failed = 0, False
        while attempt < ATTEMPTS:
            attempt += 1
            probe.slips.clear()
            outcome, detail, lost, send_failed = _attempt(probe, check, guard)
            if send_failed:  # the host could not write: tried again, failed if it persists
                continue
            if not probe.slips or outcome == "skip" or lost is not None:
                break
            slipped.append(max(probe.slips))
        if send_failed:
            detail += f" (in each of {attempt} attempts)"
        elif len(slipped) == ATTEMPTS:
            outcome = "inconclusive"
            detail = (f"the host's own frames came up to {max(slipped) * 1000:.0f} ms apart in "
                      f"each of {ATTEMPTS} attempts (the host was too slow): not judged; last "
                      f"attempt: {detail}")
        elif slipped:
            detail += (f" (attempt {attempt}: the host's own frames came up to "
                       f"{max(slipped) * 1000:.0f} ms apart before)")
        result = RuleResult(name, outcome, detail, round(time.monotonic() - start, 3), section,
                            attempt)
        results.append(result)
        if progress is not None:
            progress(result)


def _attempt(probe: Probe, check: Callable[[Probe], str], guard: SignalGuard
             ) -> tuple[str, str, str | None, bool]:
    """One run of a rule, ended by STOP: outcome, detail, why the rest cannot run, and
    whether the host failed to send (a link error, the link not lost)."""
    lost: str | None = None
    send_failed = False
    try:
        outcome, detail = "pass", check(probe)
    except RuleFailedError as err:
        outcome, detail = "fail", str(err)
    except RuleSkippedError as err:
        outcome, detail = "skip", str(err)
    except LinkLostError as err:
        outcome, detail = "fail", f"link lost: {err}"
        lost = "the link was lost"
    except LinkError as err:
        outcome, detail, send_failed = "fail", f"link error: {err}", True
    finally:
        guard.defer()  # a signal now waits for the rule's STOP
        if lost is None:
            try:
                probe.end()
            except LinkError:
                pass
        guard.rearm()  # ... and ends the run here
    return outcome, detail, lost, send_failed


def run_conformance(transport: Transport, robot: RobotProfile, *,
                    rules: Sequence[str] = (), estop_pressed: bool = False,
                    progress: Callable[[RuleResult], None] | None = None,
                    answer_s: float = ANSWER_S) -> ConformanceReport:
    """Run the rules against the controller at the other end of ``transport``.

    Parameters
    ----------
    transport : Transport
        Open link (not closed here).
    robot : RobotProfile
        The robot's geometry (``k``).
    rules : sequence of str
        Names or prefixes to run (default: all).
    estop_pressed : bool
        The e-stop was pressed before the run.
    progress : callable, optional
        Called with each result as it comes.
    answer_s : float
        How long an answer (HELLO_ACK, ERROR, PONG, an acknowledging sample) may take [s]; the
        rules that check that nothing answers wait as long. The protocol sets no bound: 0.3 s
        by default, more for a controller behind a slow adapter or a loaded host.

    Returns
    -------
    ConformanceReport
    """
    probe = Probe(transport, robot, estop_pressed, answer_s)
    results: list[RuleResult] = []
    # a signal (SIGTERM, Ctrl-\ ...) unwinds through the rule's STOP below like Ctrl-C,
    # instead of ending the process with the wheels turning
    guard = SignalGuard()
    try:
        guard.check()
        _run_rules(probe, rules, results, progress, guard)
    finally:
        guard.defer()
        guard.restore()
    ack = probe.ack
    announced = {} if ack is None else {
        "version": ack.version, "telemetry_rate_hz": ack.telemetry_rate_hz,
        "watchdog_ms": ack.watchdog_ms, "wheel_limit_rpm": ack.wheel_limit_rpm}
    return ConformanceReport(tuple(results), "" if ack is None else ack.name, announced,
                             f"{transport.name} {getattr(transport, 'port', '')}".strip())
