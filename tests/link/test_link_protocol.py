"""The wire protocol: COBS, CRC, frames, the worked examples of drivers/protocol.md, and the
stream decoder on damaged input (including a hypothesis property test)."""

from __future__ import annotations

import re

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mecanum_hil.link import protocol as proto
from mecanum_hil.link.can_link import CanCodec

NAMESPACE = {name: getattr(proto, name) for name in
             ("Hello", "HelloAck", "Command", "Stop", "Heartbeat", "Ping", "Pong", "Telemetry",
              "ErrorMsg", "EstopReset")}


def _examples(text: str):
    """(message, {"raw": bytes, "wire": bytes, "can": [(id, bytes)]}) from the document."""
    out = []
    text = "\n".join(ln for ln in text.splitlines() if not ln.startswith("```"))
    for block in re.split(r"\n\s*\n", text):
        lines = [ln.strip() for ln in block.strip().splitlines()]
        if not lines or not lines[0].startswith("message:"):
            continue
        msg = eval(lines[0].split(":", 1)[1], {}, dict(NAMESPACE))  # test-only: our own doc
        fields: dict = {"can": []}
        for ln in lines[1:]:
            key, _, value = ln.partition(":")
            if key == "can":
                fid, *data = value.split()
                fields["can"].append((int(fid, 16), bytes.fromhex("".join(data))))
            elif key in ("raw", "wire"):
                fields[key] = bytes.fromhex(value.replace(" ", ""))
        out.append((msg, fields))
    return out


def test_crc_and_cobs_reference_values():
    assert proto.crc16(b"123456789") == 0x29B1
    assert proto.cobs_encode(b"\x00") == b"\x01\x01"
    assert proto.cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    data = bytes(range(1, 256))  # 255 non-zero bytes: a full 254-block and a rest
    enc = proto.cobs_encode(data)
    assert enc[0] == 0xFF and 0 not in enc and proto.cobs_decode(enc) == data
    assert proto.cobs_decode(b"\x05\x11") is None  # block runs past the end


def test_worked_examples_in_protocol_md_match_the_encoder(repo):
    examples = _examples((repo / "drivers" / "protocol.md").read_text())
    serial = [(m, f) for m, f in examples if "wire" in f]
    can = [(m, f) for m, f in examples if f["can"]]
    assert len(serial) == 10 and len(can) == 7
    for msg, f in serial:
        assert proto.pack_frame(msg) == f["raw"], msg
        assert proto.encode(msg) == f["wire"], msg
        assert proto.StreamDecoder().feed(f["wire"]) == [msg]
    codec = CanCodec()
    for msg, f in can:
        assert codec.encode(msg) == f["can"], msg
        decoded = [codec.decode(fid, data) for fid, data in f["can"]]
        assert decoded[-1] == msg


def test_every_message_round_trips_through_the_decoder():
    msgs = [proto.Hello(), proto.Command(12.25, -3.5, 270.0, 7), proto.Stop(8),
            proto.Heartbeat(9), proto.Ping(0xFFFFFFFF, 10),
            proto.HelloAck(proto.PROTOCOL_VERSION, 1000, 250, "x" * 32, 11, 130.5),
            proto.EstopReset(14),
            proto.Telemetry(2**32 - 1, (1.5, -2.5, 3.5, -4.5), 0xF, 65535, 65535),
            proto.Pong(3, 12), proto.ErrorMsg(255, "é", 13)]
    dec = proto.StreamDecoder()
    assert dec.feed(b"".join(proto.encode(m) for m in msgs)) == msgs
    assert dec.counts == proto.DecodeCounts()


def _counts_after(data: bytes) -> tuple[list, proto.DecodeCounts]:
    dec = proto.StreamDecoder()
    return dec.feed(data), dec.counts


def test_bad_frames_are_counted_by_reason_and_skipped():
    good = proto.Telemetry(1, (1.0, 2.0, 3.0, 4.0), 0, 0, 5)
    raw = proto.pack_frame(good)
    bad_crc = raw[:-1] + bytes([raw[-1] ^ 0xFF])
    unknown = bytearray(proto.pack_frame(proto.Stop(1)))
    unknown[1] = 0x42
    unknown[-2:] = proto.crc16(bytes(unknown[:-2])).to_bytes(2, "little")
    wrong_version = bytearray(raw)
    wrong_version[0] = 7
    wrong_version[-2:] = proto.crc16(bytes(wrong_version[:-2])).to_bytes(2, "little")
    short_body = bytearray(proto.pack_frame(proto.Command(1, 2, 3, 1)))[:-6]
    short_body += proto.crc16(bytes(short_body)).to_bytes(2, "little")

    def framed(b):
        return b"\x00" + proto.cobs_encode(bytes(b)) + b"\x00"

    cases = {
        "crc": framed(bad_crc),
        "unknown_type": framed(unknown),
        "version": framed(wrong_version),
        "malformed": framed(short_body),
    }
    for kind, data in cases.items():
        out, counts = _counts_after(data + proto.encode(good))
        assert out == [good], kind
        assert getattr(counts, kind) == 1, (kind, counts)
    # truncated frame: the start of a frame, cut, then a new frame
    out, counts = _counts_after(proto.encode(good)[:-9] + proto.encode(good))
    assert out == [good] and counts.malformed + counts.crc == 1
    # a run of bytes without a delimiter longer than any frame is dropped as garbage
    out, counts = _counts_after(b"\x07" * 500 + proto.encode(good))
    assert out == [good] and counts.garbage_bytes >= 500


def test_hello_of_another_version_is_still_understood():
    # HELLO's empty body and HELLO_ACK's version byte are the same in every version; the rest
    # of another version's HELLO_ACK is not read
    data = proto.encode(proto.Hello(version=1)) + proto.encode(proto.HelloAck(version=3))
    out, counts = _counts_after(data)
    assert out == [proto.Hello(version=1), proto.HelloAck(3, 0, 0, "", 0)]
    assert counts.version == 0


def test_hello_with_a_body_is_malformed():
    # finding 6: a HELLO with a non-empty body was accepted
    raw = bytearray(proto.pack_frame(proto.Hello()))[:-2] + b"\x01\x02"
    raw += proto.crc16(bytes(raw)).to_bytes(2, "little")
    out, counts = _counts_after(b"\x00" + proto.cobs_encode(bytes(raw)) + b"\x00")
    assert out == [] and counts.malformed == 1


def test_oversized_values_are_packed_as_infinity_never_raising():
    # finding 1: 3.4e38 overflowed float32 packing and killed sim-robot
    frame = proto.encode(proto.Telemetry(0, (1e39, -1e39, float("nan"), 0.0)))
    (tlm,) = proto.StreamDecoder().feed(frame)
    assert tlm.wheel_rpm[0] == float("inf") and tlm.wheel_rpm[1] == float("-inf")
    (cmd,) = proto.StreamDecoder().feed(proto.encode(proto.Command(3.5e38, 0.0, 90.0)))
    assert cmd.n_rpm == float("inf")


@pytest.mark.parametrize(("fields", "ok"), [
    ((130.0, 0.0, 90.0), True), ((-130.0, 0.0, 270.0), True), ((130.001, 0.0, 90.0), False),
    ((5000.0, 0.0, 90.0), False), ((1e30, 0.0, 90.0), False), ((0.0, 0.0, 700.0), False),
    ((float("nan"), 0.0, 90.0), False), ((0.0, float("inf"), 90.0), False),
    ((0.0, 0.0, float("-inf")), False), ((5e-324, -1e-45, 90.0), True)])
def test_command_problem_is_the_documented_rule(fields, ok):
    assert (proto.command_problem(*fields, k=0.465 / 0.102, wheel_limit_rpm=130.0) is None) == ok


message_strategy = st.one_of(
    st.builds(proto.Command, st.floats(-300, 300, width=32), st.floats(-300, 300, width=32),
              st.floats(-360, 360, width=32), seq=st.integers(0, 65535)),
    st.builds(proto.Telemetry, st.integers(0, 2**32 - 1),
              st.tuples(*[st.floats(-300, 300, width=32)] * 4),
              st.integers(0, 15), st.integers(0, 65535), st.integers(0, 65535)),
    st.builds(proto.Stop, st.integers(0, 65535)),
    st.builds(proto.Ping, st.integers(0, 2**32 - 1), st.integers(0, 65535)),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.binary(max_size=80), message_strategy), min_size=1, max_size=8),
       st.binary(max_size=80), st.integers(1, 40))
def test_every_valid_frame_embedded_in_garbage_is_recovered(pieces, tail, chunk):
    stream = b"".join(junk + proto.encode(msg) for junk, msg in pieces) + tail
    dec = proto.StreamDecoder()
    out = []
    for i in range(0, len(stream), chunk):  # arbitrary read sizes
        out += dec.feed(stream[i:i + chunk])
    expected = [msg for _, msg in pieces]
    # every frame comes out, in order; garbage can only add (CRC-valid by chance) frames
    it = iter(out)
    assert all(any(got == want for got in it) for want in expected)


@pytest.mark.parametrize("chunk", [1, 3, 1000])
def test_random_bytes_never_raise(chunk):
    import random

    rng = random.Random(chunk)
    data = bytes(rng.getrandbits(8) for _ in range(20000))
    dec = proto.StreamDecoder()
    for i in range(0, len(data), chunk):
        dec.feed(data[i:i + chunk])
    assert len(dec._buf) <= proto.MAX_ENCODED_BYTES


def test_stop_goes_before_a_backlog_of_stale_commands():
    """With the device not reading, a queued STOP replaces the backlog instead of waiting."""
    from mecanum_hil.link.protocol import Command, Stop, StreamDecoder, encode
    from mecanum_hil.link.serial_link import PendingOutput

    taken = bytearray()
    accepting = {"n": 0}

    def write(data: bytes) -> int:
        n = min(len(data), accepting["n"])
        if n == 0:
            raise BlockingIOError
        taken.extend(data[:n])
        accepting["n"] -= n
        return n

    out = PendingOutput(write, "test", limit=4096)
    frames = [encode(Command(60.0, 0.0, 90.0)) for _ in range(20)]
    accepting["n"] = len(frames[0]) // 2  # half a frame goes out, then the device stalls
    for f in frames:
        out.queue(f)
    out.urgent(encode(Stop()), resync=b"\x00")
    accepting["n"] = 10_000
    out.flush()
    decoded = list(StreamDecoder().feed(bytes(taken)))
    assert [type(m).__name__ for m in decoded] == ["Stop"]
