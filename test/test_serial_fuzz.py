"""Fuzzing the streaming parser: random bytes, flipped bits, truncated and concatenated
frames, > 10^6 bytes per run. Nothing escapes, nothing with a bad CRC is accepted, and a
valid frame after garbage is always recovered.

One documented exception (docs/serial_protocol.md, "Resynchronisation"): a frame cut short
can be completed by the first byte(s) of what follows when they happen to equal the
missing ones; the parser then delivers the cut frame (byte-identical to what was sent) and
the next frame loses its start. The tests allow exactly that and nothing else.
"""

from __future__ import annotations

import itertools
import random

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from asgp_ros.serial import protocol as proto

FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.too_slow])


def _random_frame(rng: random.Random, seq: int) -> bytes:
    msg_type = rng.randrange(256)
    payload = bytes(rng.randrange(256) for _ in range(rng.randrange(proto.MAX_PAYLOAD + 1)))
    return proto.encode_frame(msg_type, seq, payload)


IDLE = bytes(proto.MAX_FRAME)  # line idle long enough to complete any claimed frame


def _encoded(frames: list[proto.Frame]) -> list[bytes]:
    return [proto.encode_frame(f.type, f.seq, f.payload) for f in frames]


def _straddles(stream: bytes, boundary: int, frame: bytes) -> bool:
    """``frame`` occurs in ``stream`` across ``boundary`` (a cut frame completed by chance)."""
    start = stream.find(frame, max(0, boundary - len(frame) + 1))
    return 0 <= start < boundary < start + len(frame)


def make_stream(rng: random.Random, n_bytes: int
                ) -> tuple[bytes, list[bytes], set[bytes], set[bytes]]:
    """A hostile byte stream of about n_bytes: (stream, the intact frames hidden in it in
    order, the originals of the truncated frames, the bit-flipped frames).

    Segments: random garbage (biased towards sync bytes), intact frames, frames with one
    flipped bit, truncated frames, and back-to-back intact frames.
    """
    out = bytearray()
    intact: list[bytes] = []
    truncated: set[bytes] = set()
    flipped: set[bytes] = set()
    seq = 0
    while len(out) < n_bytes:
        kind = rng.random()
        if kind < 0.25:
            out += bytes(rng.choice((0xA5, 0x5A, rng.randrange(256)))
                         for _ in range(rng.randrange(1, 60)))
        elif kind < 0.55:
            for _ in range(rng.randrange(1, 4)):  # concatenated
                f = _random_frame(rng, seq)
                seq += 1
                out += f
                intact.append(f)
        elif kind < 0.8:
            f = bytearray(_random_frame(rng, seq))
            bit = rng.randrange(len(f) * 8)
            f[bit // 8] ^= 1 << (bit % 8)
            out += f
            flipped.add(bytes(f))
        else:
            f = _random_frame(rng, seq)
            out += f[:rng.randrange(1, len(f))]
            truncated.add(f)
    return bytes(out) + IDLE, intact, truncated, flipped


def test_one_megabyte_hostile_stream():
    rng = random.Random(20180521)
    stream, intact, truncated, flipped = make_stream(rng, 1_000_000)
    assert len(stream) >= 1_000_000
    parser = proto.StreamParser()
    got: list[proto.Frame] = []
    pos = 0
    while pos < len(stream):  # random read sizes, like a serial port
        n = rng.choice((1, 7, 64, 512, 4096))
        got += parser.feed(stream[pos:pos + n])
        pos += n
    delivered = _encoded(got)
    # every intact frame recovered, in order ...
    it = iter(delivered)
    missing = [f for f in intact if f not in it]  # subsequence test
    assert not missing
    # ... and nothing else but cut frames completed by chance, byte-identical to the sent ones
    extra = set(delivered) - set(intact)
    assert extra <= truncated
    assert not set(delivered) & flipped
    assert parser.crc_errors > 0 and parser.bytes_dropped > 0
    assert parser.pending <= proto.MAX_FRAME


@FUZZ
@given(data=st.binary(max_size=2000), cuts=st.lists(st.integers(0, 2000), max_size=8))
def test_random_bytes_never_raise_and_only_valid_crcs_pass(data, cuts):
    parser = proto.StreamParser()
    bounds = sorted({0, len(data), *(c for c in cuts if c < len(data))})
    frames = []
    for a, b in itertools.pairwise(bounds):
        frames += parser.feed(data[a:b])
    for f in frames:  # each delivered frame occurs verbatim, valid CRC included, in the input
        assert proto.encode_frame(f.type, f.seq, f.payload) in data
        assert len(f.payload) <= proto.MAX_PAYLOAD
    assert parser.pending <= proto.MAX_FRAME


frame_st = st.builds(proto.encode_frame, st.integers(0, 255), st.integers(0, 255),
                     st.binary(max_size=proto.MAX_PAYLOAD))


@FUZZ
@given(garbage=st.binary(max_size=300), frame=frame_st)
def test_valid_frame_after_garbage_is_recovered(garbage, frame):
    stream = garbage + frame + IDLE
    encoded = _encoded(proto.StreamParser().feed(stream))
    assert frame in encoded or any(_straddles(stream, len(garbage), e) for e in encoded)


@FUZZ
@given(frame=frame_st, bit=st.integers(0, 10_000), follow=frame_st)
def test_flipped_bit_is_rejected_and_next_frame_recovered(frame, bit, follow):
    bad = bytearray(frame)
    bit %= len(bad) * 8
    bad[bit // 8] ^= 1 << (bit % 8)
    encoded = _encoded(proto.StreamParser().feed(bytes(bad) + follow + IDLE))
    assert frame not in encoded or frame == follow
    assert bytes(bad) not in encoded
    assert encoded[-1:] == [follow]


@FUZZ
@given(frame=frame_st, cut=st.integers(1, 100), follow=frame_st)
def test_truncated_frame_then_valid_frame(frame, cut, follow):
    cut = min(cut, len(frame) - 1)
    encoded = _encoded(proto.StreamParser().feed(frame[:cut] + follow + IDLE))
    if (frame[:cut] + follow).startswith(frame):
        assert encoded[:1] == [frame]  # completed by chance: exactly the frame sent
    else:
        assert encoded == [follow]


@FUZZ
@given(frames=st.lists(frame_st, min_size=1, max_size=20), chunk=st.integers(1, 64))
def test_concatenated_frames_any_chunking(frames, chunk):
    stream = b"".join(frames)
    parser = proto.StreamParser()
    got = []
    for i in range(0, len(stream), chunk):
        got += parser.feed(stream[i:i + chunk])
    assert [proto.encode_frame(f.type, f.seq, f.payload) for f in got] == frames
    assert parser.crc_errors == 0 and parser.bytes_dropped == 0
