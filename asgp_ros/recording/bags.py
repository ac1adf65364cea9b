"""Bag reading and writing with the pure-Python ``rosbags`` library (no ROS install needed).

Reading: ROS 1 ``.bag`` files, ROS 2 bags (a directory with ``metadata.yaml``; sqlite3 or
mcap storage) through one function, ``read_streams``, into the ``RawStreams`` the core
resamples.

* joystick topic: ``sensor_msgs/Joy``; which axes are forward and turn, and their signs, is
  configurable (``JoyAxes``, command-line syntax ``--joy-axes FWD,TURN``, see
  ``parse_joy_axes``);
* velocity topic: ``geometry_msgs/TwistStamped``, ``TwistWithCovarianceStamped``, ``Twist``
  (no header: bag time) or ``nav_msgs/Odometry``; v = linear.x, omega = angular.z;
* optional ground truth: ``nav_msgs/Odometry`` (pose and twist).

Time stamps: a message's header stamp when it is valid (non-zero and within
``max_stamp_skew`` seconds of the time the bag recorded it), the bag time otherwise
(corrected by the topic's median stamp-to-bag latency, so the clocks stay consistent).

Writing (``write_bag``): generic connections and serialised messages (``BagContent``, or a
``BagSource`` that serialises itself for the format) as a ROS 2 bag (mcap by default, or
sqlite3) or a ROS 1 bag; atomically (nothing partial on failure) and reproducibly (the
same content gives the same bytes). Bag I/O does not know where the data come from: the
simulator writes its recordings through it (:func:`asgp_ros.sim.simulate.write_recording`).

Damaged bags (``recover_bag``): a recording that was killed leaves an mcap file without its
summary and footer, an SQLite file cut at a page (perhaps with a ``-wal`` or ``-journal``),
a ROS 1 bag without its index, and no ``metadata.yaml``. The storage is then scanned record
by record from the start and every complete message is kept; a partial record is dropped,
never decoded; ``BagDamage`` says what was lost (bytes, messages, time). ``read_streams``
and ``bag_topics`` do this automatically, with a warning, when the bag does not open as
indexed (a user whose chair's battery died wants the data); ``repair_bag`` writes a clean,
indexed copy (``asgp bag repair``), ``topic_stats`` the counts, rates and gaps
(``asgp bag info``).

Failures raise ``BagError`` naming the file and the problem, in one line: no such bag,
not a bag, a corrupt file with nothing recoverable, a missing topic (with the list of
topics the bag has), an unsupported message type.

Paths are checked with ``os.stat`` before anything is opened (:func:`resolve_bag`): a bag
is a regular ROS 1 ``.bag`` file or a ROS 2 bag directory whose ``metadata.yaml`` (at
most ``MAX_BAG_METADATA_BYTES``) and storage files are regular files; a FIFO, a device,
a socket, a dangling link or a directory where a file goes is refused, naming the path,
so a reader never blocks on it.
"""

from __future__ import annotations

import bisect
import bz2
import contextlib
import hashlib
import logging
import math
import mmap
import os
import re
import sqlite3
import stat
import struct
import zlib
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, TypeGuard

import numpy as np
import yaml
from numpy.typing import NDArray

from asgp_ros.common.fileio import ROS1_MAGIC, atomic_path
from asgp_ros.common.topics import (
    BAG_JOY,
    BAG_VO_TWIST,
    JOY_OVERRIDE,
    beside,
    is_override,
    namespace_of,
)
from asgp_ros.core.modelfile import file_type_problem, loads_bounded, regular_file_problem
from asgp_ros.core.quaternion import quaternion_to_yaw
from asgp_ros.core.streams import RawStreams, joy_in_range, twist_tracked, vel_in_range

# rosbags is imported where a bag is read or written, not here: ``asgp --help`` and the
# predictor node import this module, and rosbags takes about 0.1 s to load.
# zstd and lz4 are imported where a chunk needs them: they are optional (a bag without
# such chunks reads without them).

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

STORAGES = ("mcap", "sqlite3", "ros1")
CUSTOM_DATA_KEY = "asgp_ros.simulation"

TWIST_TYPES = (
    "geometry_msgs/msg/TwistStamped",
    "geometry_msgs/msg/TwistWithCovarianceStamped",
    "geometry_msgs/msg/Twist",
    "nav_msgs/msg/Odometry",
)
JOY_TYPES = ("sensor_msgs/msg/Joy",)
TRUTH_TYPES = ("nav_msgs/msg/Odometry",)
#: Largest ``metadata.yaml`` of a ROS 2 bag read (a real one is a few kB).
MAX_BAG_METADATA_BYTES = 16 * 2**20


class BagError(Exception):
    """A bag cannot be read or written as asked; the message names the file."""


class _DamagedDataError(BagError):
    """The bag's messages cannot be read as indexed (a read from a scan may recover them)."""


# ----------------------------------------------------------------------------- joystick axes
@dataclass(frozen=True)
class JoyAxes:
    """Which ``Joy.axes`` entries are the forward and turn deflections, and their signs.

    Attributes:
        forward, turn: axis indices.
        forward_sign, turn_sign: +1 or -1 (use -1 when pushing forward / left gives a
            negative value on that axis).
    """

    forward: int = 0
    turn: int = 1
    forward_sign: float = 1.0
    turn_sign: float = 1.0

    def __post_init__(self) -> None:
        if self.forward < 0 or self.turn < 0:
            raise ValueError("joystick axis indices must be >= 0")
        if self.forward == self.turn:
            raise ValueError(f"forward and turn must be different axes, both are {self.turn}")
        if self.forward_sign not in (1.0, -1.0) or self.turn_sign not in (1.0, -1.0):
            raise ValueError("joystick axis signs must be +1 or -1")

    def __str__(self) -> str:
        def one(i: int, s: float) -> str:
            return f"{'-' if s < 0 else ''}{i}"

        return f"{one(self.forward, self.forward_sign)},{one(self.turn, self.turn_sign)}"


_AXIS_RE = re.compile(r"^\s*([+-]?)\s*(\d+)\s*$")


def parse_joy_axes(spec: str, name: str = "--joy-axes") -> JoyAxes:
    """Parse the ``--joy-axes`` syntax ``FWD,TURN`` (``name``: the option or parameter
    that gave it, for the error).

    Each of FWD and TURN is an index into ``Joy.axes``, optionally prefixed with ``-`` to
    flip its sign. ``"0,1"`` (the default, as published by this package's bridge) means
    forward = axes[0], turn = axes[1]; ``"1,-0"`` means forward = axes[1],
    turn = -axes[0]; a typical gamepad's left stick is ``"1,0"``.
    """
    parts = spec.split(",")
    if len(parts) != 2:
        raise ValueError(f"{name} {spec!r}: expected FWD,TURN such as '0,1' or '1,-0'")
    parsed = []
    for part in parts:
        m = _AXIS_RE.match(part)
        if m is None:
            raise ValueError(
                f"{name} {spec!r}: {part!r} is not an axis index with an optional '-'"
            )
        parsed.append((int(m.group(2)), -1.0 if m.group(1) == "-" else 1.0))
    (f, fs), (t, ts) = parsed
    try:
        return JoyAxes(forward=f, turn=t, forward_sign=fs, turn_sign=ts)
    except ValueError as exc:
        raise ValueError(f"{name} {spec!r}: {exc}") from None


# ----------------------------------------------------------------------------- reading
def _one_line(text: object) -> str:
    """An error text on one line (library messages may span several)."""
    return " ".join(str(text).split())


def _bag_metadata(bag: Path) -> dict[str, Any]:
    """The parsed ``metadata.yaml`` of a ROS 2 bag directory (size checked first)."""
    meta_path = bag / "metadata.yaml"
    problem = regular_file_problem(meta_path, MAX_BAG_METADATA_BYTES)
    if problem == "no such file":
        raise BagError(f"{bag}: not a ROS 2 bag (a directory without metadata.yaml)")
    if problem is not None:
        raise BagError(f"{meta_path}: {problem}")
    try:
        meta = yaml.safe_load(meta_path.read_text(encoding="utf-8"))
    except (OSError, ValueError, yaml.YAMLError, RecursionError) as exc:
        raise BagError(f"{meta_path}: unreadable metadata.yaml: "
                       f"{_one_line(f'{type(exc).__name__}: {exc}')}") from exc
    info = meta.get("rosbag2_bagfile_information") if isinstance(meta, dict) else None
    if not isinstance(info, dict):
        raise BagError(f"{meta_path}: not the metadata of a ROS 2 bag (no "
                       "rosbag2_bagfile_information mapping)")
    return info


def _check_bag_directory(bag: Path) -> None:
    """Refuse a ROS 2 bag whose metadata or storage files are not regular files."""
    info = _bag_metadata(bag)
    files = info.get("relative_file_paths")
    names = files if isinstance(files, list) and all(isinstance(f, str) for f in files) else []
    for name in names:
        problem = regular_file_problem(bag / name)
        if problem is not None:
            raise BagError(f"{bag / name}: {problem} (a storage file of the bag {bag})")
    try:
        entries = list(os.scandir(bag))
    except OSError as exc:
        raise BagError(f"{bag}: cannot list the bag directory: {exc.strerror}") from exc
    for entry in entries:  # whatever else a reader might open
        try:
            mode = os.stat(entry.path).st_mode
        except OSError:
            continue  # not named by the metadata (checked above): never opened
        if not stat.S_ISDIR(mode) and (problem := file_type_problem(mode)) is not None:
            raise BagError(f"{entry.path}: {problem} (in the bag {bag})")


def _bag_mode(p: Path) -> int:
    """``os.stat(p).st_mode``, or a BagError naming ``p`` (missing, unreadable)."""
    try:
        return os.stat(p).st_mode
    except FileNotFoundError:
        raise BagError(f"{p}: no such bag") from None
    except (OSError, ValueError) as exc:
        raise BagError(f"{p}: cannot be read: "
                       f"{_one_line(getattr(exc, 'strerror', None) or exc)}") from None


def resolve_bag(path: str | os.PathLike[str]) -> Path:
    """The bag ``path`` names, checked with ``os.stat`` before anything is opened.

    A ROS 1 ``.bag`` file, a ROS 2 bag directory, or a storage file inside one (which
    stands for its directory).

    Raises:
        BagError: no such path, not a bag, or a FIFO / device / socket / dangling link
            where a bag or one of its files should be (naming that path).
    """
    p = Path(path)
    mode = _bag_mode(p)
    if stat.S_ISDIR(mode):
        _check_bag_directory(p)
        return p
    problem = file_type_problem(mode)
    if problem is not None:
        raise BagError(f"{p}: {problem}: a bag is a ROS 1 .bag file or a ROS 2 bag directory")
    if p.suffix in (".mcap", ".db3") and os.path.lexists(p.parent / "metadata.yaml"):
        bag = p.parent if str(p.parent) else Path(".")
        _check_bag_directory(bag)
        return bag  # a ROS 2 bag's storage file: read the bag it belongs to
    if p.suffix != ".bag":
        raise BagError(
            f"{p}: not a bag: expected a ROS 1 .bag file or a ROS 2 bag directory "
            "(with metadata.yaml)"
        )
    _check_ros1_magic(p)
    return p


def _content_digest(files: list[Path]) -> str:
    """A digest of the storage files' sizes and of their first and last MiB: the same for a
    byte-for-byte copy, different for another recording (its messages' data differ)
    without reading a whole bag. A repaired or converted copy has other bytes: the
    messages' digests (:func:`message_digests`) tell it."""
    h = hashlib.sha256()
    for f in files:
        with open(f, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            h.update(size.to_bytes(8, "little"))
            h.update(fh.read(1 << 20))
            if size > 2 << 20:
                fh.seek(size - (1 << 20))
                h.update(fh.read(1 << 20))
    return h.hexdigest()


#: The fewest messages of a topic a digest of its start covers: a topic's digests are of
#: its first 16, 32, 64, ... messages and of all of them (:func:`message_digests`).
HEAD_MESSAGES = 16


def message_digests(bag_ns: Sequence[int], digests: Sequence[bytes]) -> dict[str, Any]:
    """What identifies one topic's messages as read: their bag times and each message's
    digest (of its type and serialised bytes), sorted by (time, digest), so that the order
    a reader gives messages of one time in does not count. ``{"n": count, "all": digest
    of them all, "heads": digests of the first HEAD_MESSAGES * 2**i}``: a copy cut short
    holds the other's first messages (:func:`recording_relation`). A repair keeps the
    times and bytes, and so does a conversion between mcap and sqlite3."""
    n = len(bag_ns)
    t = np.asarray(bag_ns, dtype=np.int64).reshape(-1)
    d = np.frombuffer(b"".join(digests), dtype="S16")
    if n > 1 and not bool(np.all(t[1:] > t[:-1])):  # else in order already
        order = np.lexsort((d, t))
        t, d = t[order], d[order]
    rec = np.empty(n, dtype=[("t", ">i8"), ("d", "S16")])
    rec["t"], rec["d"] = t, d
    buf = rec.tobytes()
    size = rec.dtype.itemsize
    h = hashlib.sha256()
    heads: list[str] = []
    done, k = 0, HEAD_MESSAGES
    while k <= n:
        h.update(buf[size * done:size * k])
        heads.append(h.hexdigest()[:16])  # 64 bits: a model file keeps them per bag
        done, k = k, 2 * k
    h.update(buf[size * done:])
    return {"n": n, "all": h.hexdigest()[:32], "heads": heads}


def _topic_digests(ident: Mapping[str, Any]) -> dict[str, tuple[int, str, list[str]]]:
    """The well-formed message digests of an identity, by topic, of topics with messages
    (a foreign file's record may be of any shape: nothing else counts)."""
    out: dict[str, tuple[int, str, list[str]]] = {}
    msgs = ident.get("messages")
    if not isinstance(msgs, dict):
        return out
    for topic, d in msgs.items():
        if not isinstance(d, dict):
            continue
        n, full, heads = d.get("n"), d.get("all"), d.get("heads")
        if isinstance(n, int) and not isinstance(n, bool) and n > 0 and isinstance(full, str) \
                and isinstance(heads, list) and all(isinstance(x, str) for x in heads):
            out[str(topic)] = (n, full, heads)
    return out


def recording_relation(a: Mapping[str, Any], b: Mapping[str, Any]
                       ) -> Literal["same", "start", "other"] | None:
    """How the recordings of two :func:`recording_identity` records relate by the
    messages read from both, on the topics both have messages on: "same" (every message
    alike: a copy, repaired, or converted between mcap and sqlite3), "start" (on every
    such topic one holds the other's first messages, at least HEAD_MESSAGES: a copy cut
    short, a repair of an unfinished copy), "other"; None when no topic was read from both
    (a record without messages' digests: older model files)."""
    ta, tb = _topic_digests(a), _topic_digests(b)
    common = sorted(ta.keys() & tb.keys())
    if not common:
        return None
    if all(ta[t][:2] == tb[t][:2] for t in common):
        return "same"
    for t in common:
        (na, _, ha), (nb, _, hb) = ta[t], tb[t]
        i = (min(na, nb) // HEAD_MESSAGES).bit_length() - 1
        if not (0 <= i < min(len(ha), len(hb))) or ha[i] != hb[i]:
            return "other"
    return "start"


def _match(mine: Mapping[str, Any], ident: object) -> Literal["same", "start"] | None:
    """"same" or "start" when ``ident`` describes the recording ``mine`` does or one
    sharing its start, else None. The messages decide where both have them; else, where
    both have a digest of the storage files, those (a new recording saved where a trained
    one was is not that one, and a byte-for-byte copy elsewhere is); else the real path."""
    if not isinstance(ident, dict):
        return None
    relation = recording_relation(mine, ident)
    if relation is not None:
        return None if relation == "other" else relation
    key = "content" if isinstance(ident.get("content"), str) and "content" in mine \
        else "path"
    return "same" if isinstance(ident.get(key), str) and ident.get(key) == mine.get(key) \
        else None


def _recording_keys(path: str | os.PathLike[str]) -> list[tuple[object, ...]]:
    """What identifies the recording ``path`` names before it is read: its real path (a
    symbolic link or a storage file stands for its bag), and a digest of its storage files
    (a byte-for-byte copy of it is the same recording; two simulated bags may start at one
    time and hold as many messages in files of one size, so metadata alone cannot tell)."""
    try:
        bag = resolve_bag(path)
    except BagError:
        return [("path", os.path.realpath(path))]  # the reader says what is wrong
    keys: list[tuple[object, ...]] = [("path", os.path.realpath(bag))]
    with contextlib.suppress(OSError):
        files = ([bag] if not bag.is_dir() else
                 sorted(f for f in bag.iterdir()
                        if f.suffix in (".mcap", ".db3") and f.is_file()))
        if files:
            keys.append(("content", _content_digest(files)))
    return keys


def recording_identity(path: str | os.PathLike[str],
                       messages: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """What identifies the recording ``path`` names, for a model file's record of its
    training data: its real path, the digest of its storage files, and, once its messages
    were read, their digests by topic (``messages``: :attr:`RawStreams.digests`), which a
    repaired or converted copy shares (:func:`find_recording`)."""
    out: dict[str, Any] = {str(k[0]): str(k[1]) for k in _recording_keys(path)}
    if messages:
        out["messages"] = {str(t): dict(d) for t, d in messages.items()}
    return out


def find_recording(path: str | os.PathLike[str] | Mapping[str, Any],
                   identities: Collection[object]) -> Literal["same", "start"] | None:
    """Whether ``path`` (or the :func:`recording_identity` of one, read once for several
    questions) is one of the recordings ``identities`` describe (records of
    :func:`recording_identity`; anything else in them, from a foreign file, matches
    nothing): "same", "start" (it and one of them share their first messages: one is a
    copy of the other cut short), or None (:func:`recording_relation`)."""
    mine = path if isinstance(path, Mapping) else recording_identity(path)
    found = {_match(mine, ident) for ident in identities}
    return "same" if "same" in found else ("start" if "start" in found else None)


def repeated_recording(named: Sequence[tuple[str, Mapping[str, Any]]]
                       ) -> tuple[str, str, Literal["same", "start"]] | None:
    """The first two of ``named`` ((name, :func:`recording_identity`)) that are one
    recording, or share their start (:func:`find_recording`), with how; or None."""
    for j, (name, ident) in enumerate(named):
        for earlier, other in named[:j]:
            how = _match(ident, dict(other))
            if how is not None:
                return earlier, name, how
    return None


def same_recording(paths: Collection[str | os.PathLike[str]]) -> tuple[str, str] | None:
    """The first two of ``paths`` that are one recording (the same bag given twice, by a
    symbolic link, its storage file or a byte-for-byte copy), or None, from what tells
    them before they are read; a repaired or converted copy is told once they are
    (:func:`repeated_recording` of their identities with the messages' digests). Training
    or testing on a recording twice counts its rows twice, and one in both a train and a
    test set tests a model on its own data."""
    seen: dict[tuple[object, ...], str] = {}
    for p in paths:
        keys = _recording_keys(p)
        for key in keys:
            if key in seen:
                return seen[key], str(p)
        for key in keys:
            seen[key] = str(p)
    return None


def repeated_text(twice: tuple[str, str, str], advice: bool = True) -> str:
    """The refusal of a recording given twice (:func:`repeated_recording`), naming both
    (and, with ``advice``, what to give instead)."""
    first, second, how = twice
    if how == "same":
        return (f"{second}: the same recording as {first} (the same messages: a copy, "
                "repaired or converted)" + ("; give each once" if advice else ""))
    return (f"{second}: begins with the same messages as {first} (one is the other cut "
            "short: a copy of an unfinished recording, or a repair of one)"
            + ("; give the longer one alone" if advice else ""))


def _check_ros1_magic(p: Path) -> None:
    """A ROS 1 bag starts with its version line. Checked here in 13 bytes because the
    reader looks for the end of that line with ``readline()``: in a file of zeros (a sparse
    or overwritten file) it would read the whole file looking for it."""
    try:
        with open(p, "rb") as fh:
            head = fh.read(len(ROS1_MAGIC))
    except OSError as exc:
        raise BagError(f"{p}: cannot be read: {_one_line(exc.strerror or exc)}") from None
    if head != ROS1_MAGIC:
        raise BagError(f"{p}: not a ROS 1 bag (version 2.0): it does not start with "
                       f"'#ROSBAG V2.0'")


_resolve = resolve_bag


def _stamp_ns(msg: Any) -> int:
    st = msg.header.stamp
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)


#: A message stamped this much (s) longer before it was recorded than its stream's median
#: latency is a stale reading delivered late: it is dropped, as the live predictor refuses
#: a sample stamped ``reset_jump_s`` (1 s) behind the newest (a clock step moves the bag
#: time and the stamps together, and keeps the latency). One stamped this much *after* the
#: stream's usual latency says would have it (a stamp the recorder's clock had not reached)
#: is no time of the message: its bag time is used. A stream whose median latency differs
#: from the joystick's by more than this is stamped on another clock than the recorder's (a
#: camera computer not synchronised): its bag times are used.
MAX_EXTRA_LATENCY = 1.0

#: A bag time this much (s) behind the messages written before it, in the order the
#: recorder wrote them, with the messages after it staying behind (the medians of the
#: :data:`_STEP_WINDOW` messages on either side differ by as much: one stray time is no
#: step), is the recorder's clock stepped back: NTP setting a laptop's clock that ran
#: ahead. Sorted by time, as every reader sorts a bag, the two timelines interleave.
CLOCK_STEP_BACK_S = 0.5
_STEP_WINDOW = 5
#: The parts of a recording whose clock stepped back are read one after another; a later
#: part that would overlap the one before is moved forward to start this long (s) after it
#: ends (a gap: the resampler joins nothing across it).
PART_GAP_S = 10.0
#: The warnings of reading each part are given for this many parts (a recording of
#: thousands of steps would say thousands of lines).
_PARTS_SAID = 3


def clock_parts(times_ns: Sequence[int] | NDArray[np.int64],
                connections: Sequence[int] | NDArray[np.int64] | None = None
                ) -> NDArray[np.int64]:
    """The part of the recording each message belongs to, given the bag times of all its
    messages in the order they were written: a new part starts where the recorder's clock
    stepped back (:data:`CLOCK_STEP_BACK_S`).

    ``connections``: each message's connection. A step is then kept only where the most
    frequent connection's own messages step back too: a clock step moves every topic,
    while a bag written topic by topic, or one whose bag times are the header stamps of a
    topic arriving late, goes back between topics only. Steps closer together than
    :data:`_STEP_WINDOW` messages are one (a message timed before the step and written
    after it)."""
    t = np.asarray(times_ns, dtype=np.int64).reshape(-1)
    parts = np.zeros(t.size, dtype=np.int64)
    tol = round(CLOCK_STEP_BACK_S * 1e9)

    def steps_back(x: NDArray[np.int64], i: int) -> bool:
        before, after = x[max(0, i - _STEP_WINDOW):i], x[i:i + _STEP_WINDOW]
        return bool(min(before.size, after.size) >= 3
                    and np.median(after) < np.median(before) - tol)

    ref_pos: NDArray[np.int64] | None = None
    if connections is not None and t.size:
        c = np.asarray(connections).reshape(-1)
        values, counts = np.unique(c, return_counts=True)
        ref_pos = np.flatnonzero(c == values[int(np.argmax(counts))])
    last = -_STEP_WINDOW - 1
    for i in np.flatnonzero(t[1:] < t[:-1] - tol) + 1:
        if i - last <= _STEP_WINDOW or not steps_back(t, int(i)):
            continue
        if ref_pos is not None:  # the reference topic's messages around position i
            j = int(np.searchsorted(ref_pos, i))
            if not steps_back(t[ref_pos], j):
                continue
        parts[i:] += 1
        last = int(i)
    return parts


def message_parts(messages: Sequence[tuple[int, int, Any]]) -> NDArray[np.int64]:
    """:func:`clock_parts` of a scan's messages (connection id, bag time, data) in the
    order they were written."""
    return clock_parts([m[1] for m in messages], [m[0] for m in messages])


def clock_steps_text(times_ns: Sequence[int] | NDArray[np.int64],
                     parts: NDArray[np.int64]) -> str:
    """What :func:`clock_parts` found, in a sentence (times in record order)."""
    t = np.asarray(times_ns, dtype=np.int64).reshape(-1)
    starts = np.flatnonzero(np.diff(parts)) + 1
    steps = "; ".join(f"{(t[i - 1] - t[i]) * 1e-9:.1f} s at bag time {t[i - 1] * 1e-9:.3f} "
                      f"(message {i + 1} as written)" for i in starts[:5])
    more = f" and {starts.size - 5} more" if starts.size > 5 else ""
    return (f"the recorder's clock stepped back {starts.size} time(s) during the recording "
            f"({steps}{more})")


def _lead(latency: float) -> str:
    return f"{abs(latency):.3f} s {'before' if latency >= 0 else 'after'}"


def _choose_times(name: str, stamp_ns: NDArray[np.int64] | None, bag_ns: NDArray[np.int64],
                  max_skew: float, source: str, reference: float | None = None,
                  warn: bool = True) -> tuple[FloatArray, BoolArray, float | None]:
    """Header stamps where valid, bag time (minus the median latency) elsewhere, seconds;
    which messages are stale (MAX_EXTRA_LATENCY), to be dropped; and the median latency
    (bag time - stamp, s; None without valid stamps).

    ``reference``: the joystick's median latency (the serial bridge stamps on the
    recorder's computer); a stream whose own differs by more than MAX_EXTRA_LATENCY is read
    on its bag times minus the reference. ``warn``: say what was done (False: silently)."""
    say = log.warning if warn else log.debug
    bag = bag_ns.astype(np.float64) * 1e-9
    fresh = np.ones(bag.shape, dtype=bool)
    on_bag = bag - reference if reference is not None else bag  # (the joystick's clock)
    if stamp_ns is None:
        return on_bag, fresh, None
    stamp = stamp_ns.astype(np.float64) * 1e-9
    valid = (stamp_ns > 0) & (np.abs(stamp - bag) <= max_skew)
    if not valid.any():
        say("%s: %s has no valid header stamps; using bag time", source, name)
        return on_bag, fresh, None
    if not valid.all():
        say("%s: %s: %d of %d header stamps invalid (zero or > %.1f s from bag "
                    "time); using bag time for those", source, name, int((~valid).sum()),
                    valid.size, max_skew)
    latency = float(np.median(bag[valid] - stamp[valid]))
    if reference is not None and abs(latency - reference) > MAX_EXTRA_LATENCY:
        say("%s: %s is stamped %s its recording times, the joystick %s: its "
                    "stamps are not on the recorder's clock (a computer not synchronised); "
                    "its bag times are used", source, name, _lead(latency), _lead(reference))
        return bag - reference, fresh, reference
    ahead = valid & (bag - stamp < latency - MAX_EXTRA_LATENCY)
    if ahead.any():
        say("%s: %s: %d of %d messages stamped more than %.1f s later than their "
                    "recording times say (a stamp the clock had not reached); using bag "
                    "time for those", source, name, int(ahead.sum()), ahead.size,
                    MAX_EXTRA_LATENCY)
        valid &= ~ahead
    fresh = ~(valid & (bag - stamp - latency > MAX_EXTRA_LATENCY))
    if not fresh.all():
        say("%s: %s: %d of %d messages stamped more than %.1f s before they were "
                    "recorded, beyond the usual %.3f s (stale readings delivered late); "
                    "they are dropped", source, name, int((~fresh).sum()), fresh.size,
                    MAX_EXTRA_LATENCY, latency)
    return np.where(valid, stamp, bag - latency), fresh, latency


def _topics_listing(reader: Any) -> str:
    items = sorted({(str(c.topic), str(c.msgtype)) for c in reader.connections})
    if not items:
        return "(no topics)"
    return ", ".join(f"{t} [{m}]" for t, m in items)


def _connections(reader: Any, topic: str, allowed: tuple[str, ...], what: str,
                 source: str) -> list[Any]:
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        raise BagError(
            f"{source}: {what} topic {topic!r} not found; the bag has: {_topics_listing(reader)}"
        )
    bad = sorted({c.msgtype for c in conns if c.msgtype not in allowed})
    if bad:
        raise BagError(
            f"{source}: {what} topic {topic!r} has unsupported type {', '.join(bad)}; "
            f"supported: {', '.join(allowed)}"
        )
    return conns


def _collect(reader: Any, conns: list[Any], extract: Callable[[Any, str], tuple[Any, ...]],
             source: str
             ) -> tuple[list[int], list[tuple[Any, ...]], list[int], dict[str, Any]]:
    """The bag times, extracted rows and parts of the recording (:func:`clock_parts`; all
    0 from a reader that does not tell them) of the messages of ``conns``, and their
    digests (:func:`message_digests`: taken as they are read, not in a second pass)."""
    bag_ns: list[int] = []
    rows: list[tuple[Any, ...]] = []
    digests: list[bytes] = []
    typed: dict[str, Any] = {}  # a digest of each message type, to go on from
    try:
        for conn, timestamp, raw in reader.messages(connections=conns):
            if not (isinstance(timestamp, int) and 0 <= timestamp < 2**63):
                # an SQLite row whose time is not an integer (1.5e30 stored as REAL) or
                # beyond int64: damaged data, as the scan judges it
                raise _DamagedDataError(f"{source}: corrupt bag: a message's bag time is "
                                        f"{_one_line(repr(timestamp))[:40]}")
            msg = reader.deserialize(raw, conn.msgtype)
            bag_ns.append(int(timestamp))
            rows.append(extract(msg, conn.msgtype))
            base = typed.get(conn.msgtype)
            if base is None:
                base = typed[conn.msgtype] = hashlib.blake2b(
                    conn.msgtype.encode() + b"\0", digest_size=16)
            d = base.copy()
            d.update(raw)
            digests.append(d.digest())
    except BagError:
        raise
    except Exception as exc:  # rosbags raises several types for damaged data
        raise _DamagedDataError(f"{source}: corrupt or truncated bag: "
                       f"{_one_line(f'{type(exc).__name__}: {exc}')}") from exc
    parts_of = getattr(reader, "message_parts", None)
    parts = list(parts_of(conns)) if parts_of is not None else [0] * len(rows)
    return bag_ns, rows, parts, message_digests(bag_ns, digests)


def _warn_no_override_topic(reader: Any, topic: str, joy_topic: str, default: bool,
                            source: str) -> None:
    """Say so when the override topic asked for is not in the bag but another one may be
    (a namespaced recording), or when it was not the default (a typo). Another is named as
    the one to read only when it is the one override topic in the joystick's namespace or
    below it: a two-chair recording's other chair's overrides are not this chair's."""
    others = sorted({c.topic for c in reader.connections
                     if isinstance(c.topic, str) and c.topic != topic
                     and is_override(c.topic)})
    if others:
        space = namespace_of(joy_topic).rstrip("/") + "/"
        near = [o for o in others if o.startswith(space)]
        if len(near) == 1:
            log.warning("%s: no override topic %s, but the bag has %s: --override-topic %s "
                        "reads it (its steps are then not trained on)", source, topic,
                        ", ".join(others), near[0])
        else:
            log.warning("%s: no override topic %s; the bag has %s, %s the joystick %s's "
                        "namespace: not read (--override-topic names the one sent to the "
                        "chair of --joy-topic)", source, topic, ", ".join(others),
                        "more than one in" if near else "none in", joy_topic)
    elif not default:
        log.warning("%s: override topic %s not found; the bag has: %s", source, topic,
                    _topics_listing(reader))


def _open_reader(path: str | os.PathLike[str], topics: Collection[str] | None = None) -> Any:
    """An open rosbags reader of the bag, or a reader over a scan of it (keeping the data
    of ``topics``) when the recording was killed (no metadata.yaml) or its storage does
    not open (cut, no index)."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    try:
        bag = resolve_bag(path)
    except BagError as exc:
        if not _unfinished_ros2_bag(path):
            raise
        return _open_recovered(path, exc, topics)
    store = get_typestore(Stores.ROS1_NOETIC if bag.is_file() else Stores.ROS2_JAZZY)
    if (log_file := unapplied_log(bag)) is not None:
        # rosbags opens SQLite immutable, which ignores the log: its committed rows (half a
        # recording, killed before a checkpoint) were silently left out; the scan applies it
        return _open_recovered(bag, BagError(
            f"{bag}: {log_file.name} holds writes not yet in the database (a recorder "
            "stopped before its checkpoint)"), topics)
    try:
        reader = AnyReader([bag], default_typestore=store)
        reader.open()
    except Exception as exc:
        return _open_recovered(bag, BagError(
            f"{bag}: cannot open bag (corrupt or truncated): "
            f"{_one_line(f'{type(exc).__name__}: {exc}')}"), topics)
    odd = [c for c in reader.connections
           if not (isinstance(c.topic, str) and isinstance(c.msgtype, str))]
    if odd:  # a damaged metadata.yaml (a list, a number or a YAML alias as a name)
        with contextlib.suppress(Exception):
            reader.close()
        return _open_recovered(bag, BagError(
            f"{bag}: cannot open bag: its metadata names a topic or a message type that is "
            f"not text ({_one_line(repr(odd[0].topic))[:60]} "
            f"[{_one_line(repr(odd[0].msgtype))[:60]}])"), topics)
    return reader


def _in_record_order(path: str | os.PathLike[str], reader: Any,
                     topics: Collection[str]) -> Any:
    """``reader``; or, when the recorder's clock stepped back during the recording
    (:func:`clock_parts`), a reader over a scan of the bag in the order it was written,
    which tells each message's part: rosbags sorts a bag by time, and the two timelines
    would interleave. (A scan reader is in that order already.)"""
    from rosbags.typesys import Stores, get_typestore

    if getattr(reader, "recovered", None) is not None:
        return reader
    try:
        written = written_times(path)
    except BagError:  # what rosbags opens and the scan cannot read: not checked
        return reader
    parts = message_parts(written)
    if not (parts.size and parts[-1]):
        return reader
    reader.close()
    recovered = recover_bag(path, topics, record_order=True, listed_only=True)
    return _RecoveredReader(recovered, get_typestore(
        Stores.ROS1_NOETIC if recovered.ros1 else Stores.ROS2_JAZZY))


def written_times(path: str | os.PathLike[str]) -> list[tuple[int, int, bytes]]:
    """(connection, bag time, b"") of every message of an intact bag (the storage files its
    metadata.yaml lists), in the order written: SQLite's rows by id from the database
    itself (a scan of its pages follows every image's overflow pages: 4.6 s for a 1.5 GB
    camera bag that rosbags opens in 0.4 s), other storages from a scan of the records."""
    bag, storage, files, _listing = _storage_files(path, listed_only=True)
    if storage != "sqlite3":
        return recover_bag(path, topics=(), record_order=True, listed_only=True).messages
    out: list[tuple[int, int, bytes]] = []
    topics: dict[str, int] = {}  # one number per topic across the files
    for f in files:
        try:
            con = sqlite3.connect(f"{f.resolve().as_uri()}?immutable=1", uri=True)
            try:
                rows = con.execute("SELECT topics.name, messages.timestamp FROM messages "
                                   "JOIN topics ON messages.topic_id = topics.id "
                                   "ORDER BY messages.id")
                for name, t in rows:
                    if not (isinstance(t, int) and 0 <= t < 2**63):
                        raise BagError(f"{bag}: {f.name}: a message's bag time is "
                                       f"{_one_line(repr(t))[:40]}")
                    out.append((topics.setdefault(str(name), len(topics)), t, b""))
            finally:
                con.close()
        except sqlite3.Error as exc:
            raise BagError(f"{bag}: cannot read {f.name}: {_one_line(exc)}") from exc
    return out


def unapplied_log(bag: Path) -> Path | None:
    """The first non-empty SQLite write-ahead log or rollback journal beside a ROS 2 bag
    directory's ``.db3`` files, or None. The indexed reader (rosbags) opens SQLite as
    immutable, which reads neither: the rows committed in a ``-wal`` (a recorder killed
    before its checkpoint) would be left out without a word."""
    if not bag.is_dir():
        return None
    try:
        for entry in os.scandir(bag):
            if entry.name.endswith((".db3-wal", ".db3-journal")) and entry.is_file() \
                    and entry.stat().st_size > 0:
                return Path(entry.path)
    except OSError:
        return None
    return None


def _unfinished_ros2_bag(path: str | os.PathLike[str]) -> bool:
    """A ROS 2 bag directory (or its storage file) without metadata.yaml, which the recorder
    writes last: what a killed recording leaves."""
    p = Path(path)
    if p.suffix in (".mcap", ".db3"):
        p = p.parent if str(p.parent) else Path(".")
    try:
        return (p.is_dir() and not os.path.lexists(p / "metadata.yaml")
                and any(Path(e.name).suffix in (".mcap", ".db3") for e in os.scandir(p)))
    except OSError:
        return False


def velocity_frame_problem(frame: str, base_frame: str) -> str | None:
    """Why a twist in ``frame`` cannot be read as the chair's forward and turn rates
    (linear.x, angular.z of ``base_frame``), or None: an empty frame is taken as the base's,
    another frame (a camera's, whose x is not forward) is refused. Frames are compared as
    tf2 reads them, without a leading slash."""
    if not frame.lstrip("/") or frame.lstrip("/") == base_frame.lstrip("/"):
        return None
    return (f"twists in frame {_one_line(repr(frame))[:60]} refused: their linear.x and "
            "angular.z are the chair's forward and turn rates only in base_frame "
            f"{base_frame!r}")


def _read_topics(reader: Any, source: str, joy_topic: str, twist_topic: str,
                 truth_topic: str | None, axes: JoyAxes, override_topic: str | None = None,
                 base_frame: str = "base_link", default_override: bool = False
                 ) -> tuple[Any, ...]:
    """The raw rows of the joystick, velocity, ground-truth and (when the bag has it)
    override topics (closes ``reader``; ``default_override``: the override topic is the
    default, not said when missing). Twists in another frame than ``base_frame`` are
    lost samples, counted (``velocity_frame_problem``), as the nodes refuse them."""
    try:
        joy_conns = _connections(reader, joy_topic, JOY_TYPES, "joystick", source)
        tw_conns = _connections(reader, twist_topic, TWIST_TYPES, "velocity", source)
        tr_conns = (_connections(reader, truth_topic, TRUTH_TYPES, "ground truth", source)
                    if truth_topic else [])
        try:
            ov_conns = (_connections(reader, override_topic, JOY_TYPES, "override", source)
                        if override_topic and any(c.topic == override_topic
                                                  for c in reader.connections) else [])
        except BagError as exc:
            raise BagError(f"{exc}; --override-topic names the overrides' topic, '' reads "
                           f"the bag as if it had none") from exc
        need = max(axes.forward, axes.turn) + 1

        def joy_row(msg: Any, _t: str) -> tuple[Any, ...]:
            a = msg.axes
            if len(a) < need:
                raise BagError(
                    f"{source}: {joy_topic} has {len(a)} axes, --joy-axes {axes} needs {need}"
                )
            return (_stamp_ns(msg), axes.forward_sign * float(a[axes.forward]),
                    axes.turn_sign * float(a[axes.turn]))

        foreign: dict[str, int] = {}  # twists in another frame than base_frame, by frame

        def twist_row(msg: Any, msgtype: str) -> tuple[Any, ...]:
            """(stamp, v, omega, 1.0 tracked / 0.0 lost): a twist with covariance says
            tracking was lost as the nodes read it (vo_node's lost frames: zero, variance
            ODOM_LOST_VARIANCE), or a lost frame's zero would be learnt as the chair's; a
            twist in another frame is lost (a backward camera's: read as the chair's, a
            forward drive was learnt as a reverse one)."""
            if msgtype == "geometry_msgs/msg/Twist":
                return (0, msg.linear.x, msg.angular.z, 1.0)
            frame = str(msg.child_frame_id if msgtype == "nav_msgs/msg/Odometry"
                        else msg.header.frame_id)
            if velocity_frame_problem(frame, base_frame) is not None:
                foreign[frame] = foreign.get(frame, 0) + 1
                return (_stamp_ns(msg), math.nan, math.nan, 0.0)
            if msgtype == "geometry_msgs/msg/TwistStamped":
                return (_stamp_ns(msg), msg.twist.linear.x, msg.twist.angular.z, 1.0)
            tw, cov = msg.twist.twist, msg.twist.covariance
            v, w = float(tw.linear.x), float(tw.angular.z)
            tracked = twist_tracked(v, w, float(cov[0]), float(cov[35]))
            return (_stamp_ns(msg), v, w, 1.0 if tracked else 0.0)

        def truth_row(msg: Any, _t: str) -> tuple[Any, ...]:
            p = msg.pose.pose
            tw = msg.twist.twist
            q = p.orientation
            return (_stamp_ns(msg), p.position.x, p.position.y,
                    float(quaternion_to_yaw(q.x, q.y, q.z, q.w)), tw.linear.x, tw.angular.z)

        joy = _collect(reader, joy_conns, joy_row, source)
        vel = _collect(reader, tw_conns, twist_row, source)
        if foreign:
            # the most frequent frames, each cut short (a bag's frames are its writer's: one
            # in a distinct frame per message made an error as long as the bag)
            common = sorted(foreign, key=lambda f: (-foreign[f], f))
            frames = ", ".join(_one_line(repr(f))[:40] for f in common[:3]) + (
                f" and {len(common) - 3} other frames" if len(common) > 3 else "")
            n = sum(foreign.values())
            problem = (f"{source}: {n} of {len(vel[1])} twists on {twist_topic} are in "
                       f"frame {frames}, not base_frame {base_frame!r}: their linear.x and "
                       "angular.z are not the chair's forward and turn rates")
            if n == len(vel[1]):
                raise BagError(f"{problem}; --base-frame names the chair's frame if that is "
                               "it")
            log.warning("%s; they are read as lost samples", problem)
        truth = (_collect(reader, tr_conns, truth_row, source) if tr_conns
                 else ([], [], [], {}))
        try:
            overrides = (_collect(reader, ov_conns, lambda msg, _t: (_stamp_ns(msg),),
                                  source) if ov_conns else ([], [], [], {}))
        except (BagError, _DamagedDataError) as exc:
            raise type(exc)(
                f"{exc} (in the overrides, {override_topic}: without them the steps they "
                f"drove cannot be told apart; --override-topic '' reads the bag as if it had "
                f"none)") from exc
        if override_topic and not ov_conns:
            _warn_no_override_topic(reader, override_topic, joy_topic, default_override,
                                    source)
        return joy, vel, truth, tw_conns, overrides
    finally:
        reader.close()


@dataclass(frozen=True)
class _Stream:
    """One topic's messages as read: header stamps (None: the type has none), bag times
    (ns) and parts of the recording (:func:`clock_parts`)."""

    name: str
    stamp_ns: NDArray[np.int64] | None
    bag_ns: NDArray[np.int64]
    parts: NDArray[np.int64]


def _stream_times(streams: list[_Stream], max_skew: float, source: str
                  ) -> list[tuple[FloatArray, BoolArray]]:
    """Each stream's times (s) and which of its messages are fresh (:func:`_choose_times`),
    part by part of the recording; the first stream, the joystick, gives the others their
    reference latency. A part that would overlap the ones before it (the recorder's clock
    stepped back, and the stamps with it) is moved forward to start :data:`PART_GAP_S`
    after them, so that no two timelines interleave; one whose stamps go on from the part
    before (only the recorder's clock stepped) stays where its stamps put it."""
    n_parts = 1 + max((int(s.parts.max()) for s in streams if s.parts.size), default=0)
    times = [np.zeros(s.bag_ns.size) for s in streams]
    fresh = [np.ones(s.bag_ns.size, dtype=bool) for s in streams]
    end = -np.inf
    last = [-np.inf] * len(streams)  # each stream's newest time in the parts before
    moved, shift = 0, 0.0
    for p in range(n_parts):
        reference: float | None = None
        joy_on_bag = False  # the joystick read on bag times: so is every stream of a part
        lo, hi = np.inf, -np.inf
        overlaps = False
        for k, s in enumerate(streams):
            sel = s.parts == p
            if not sel.any():
                continue
            name = s.name if n_parts == 1 else f"{s.name} (part {p + 1} of {n_parts})"
            stamps = None if s.stamp_ns is None or (k and joy_on_bag) else s.stamp_ns[sel]
            t, f, latency = _choose_times(name, stamps, s.bag_ns[sel], max_skew, source,
                                          reference if k else None, warn=p < _PARTS_SAID)
            if k == 0:
                reference = latency
                # after a step of the recorder's clock alone, stamps and bag times differ
                # by the step: a stream on its stamps beside a joystick on bag times was
                # read that far from the stick that drove it
                joy_on_bag = latency is None and n_parts > 1
            times[k][sel], fresh[k][sel] = t, f
            if f.any():
                lo, hi = min(lo, float(t[f].min())), max(hi, float(t[f].max()))
                overlaps |= float(t[f].min()) <= last[k]
        if overlaps:
            shift = end + PART_GAP_S - lo
            for k, s in enumerate(streams):
                times[k][s.parts == p] += shift
            hi += shift
            moved += 1
        end = max(end, hi)
        for k, s in enumerate(streams):
            sel = (s.parts == p) & fresh[k]
            if sel.any():
                last[k] = max(last[k], float(times[k][sel].max()))
    if moved:  # one line, however many parts (a bag of 6,000 steps said 6,000)
        log.warning("%s: %d of the recording's %d parts overlapped the parts before them in "
                    "time: each read %.0f s after their end (the last %.3f s later than its "
                    "bag times)", source, moved, n_parts, PART_GAP_S, shift)
    if n_parts > _PARTS_SAID:
        log.warning("%s: %d parts: the warnings of reading each were given for the first %d "
                    "only", source, n_parts, _PARTS_SAID)
    return list(zip(times, fresh, strict=True))


def read_streams(
    path: str | os.PathLike[str],
    joy_topic: str = BAG_JOY,
    twist_topic: str = BAG_VO_TWIST,
    truth_topic: str | None = None,
    joy_axes: JoyAxes | str | None = None,
    max_stamp_skew: float = 10.0,
    override_topic: str | None = JOY_OVERRIDE,
    base_frame: str = "base_link",
) -> RawStreams:
    """Read the joystick, velocity (and optional ground-truth) streams of a bag.

    Args:
        path: ROS 1 ``.bag`` file, or ROS 2 bag directory (sqlite3 or mcap), or the
            storage file inside one.
        joy_topic: ``sensor_msgs/Joy`` topic.
        twist_topic: TwistStamped / TwistWithCovarianceStamped / Twist / Odometry topic.
        truth_topic: ``nav_msgs/Odometry`` ground truth, or None to skip it.
        joy_axes: axis mapping (or its ``--joy-axes`` string).
        max_stamp_skew: a header stamp further than this (s) from the bag time is invalid.
        override_topic: ``sensor_msgs/Joy`` overrides sent to the chair (the shared-control
            layer's, a planner's), if the bag has the topic: their times become
            ``RawStreams.override_t``, around which the resampler refuses the joystick (it
            is not what drove the chair); None or '' to read none. A relative name is
            resolved in ``joy_topic``'s namespace (:func:`~asgp_ros.common.topics.beside`):
            the default, ``joy_override``, is ``/joy_override`` beside ``/joy`` and
            ``/chair2/joy_override`` beside ``/chair2/joy`` (the overrides of the chair
            whose joystick is read, in a recording of several).
        base_frame: the chair's frame: a velocity message's twist in another (a camera's
            frame; the header's frame of a TwistStamped, the child frame of an Odometry;
            an empty one is taken as the chair's) is a lost sample, as the nodes refuse it.

    Returns:
        RawStreams with times in seconds on the bag's clock (header stamps where valid).

    Raises:
        BagError: missing file or topic, unsupported type, corrupt or truncated bag.
    """
    if joy_axes is None:
        joy_axes = JoyAxes()
    axes = parse_joy_axes(joy_axes) if isinstance(joy_axes, str) else joy_axes
    if override_topic:
        override_topic = beside(joy_topic, override_topic)
    default_override = override_topic == beside(joy_topic, JOY_OVERRIDE)
    wanted = [t for t in (joy_topic, twist_topic, truth_topic, override_topic) if t]
    reader = _in_record_order(path, _open_reader(path, wanted), wanted)
    recovered = getattr(reader, "recovered", None)
    source = recovered.damage.bag if recovered is not None else str(resolve_bag(path))
    try:
        collected = _read_topics(reader, source, joy_topic, twist_topic, truth_topic, axes,
                                 override_topic, base_frame, default_override)
    except _DamagedDataError as exc:  # the index opened, the data behind it are damaged
        if recovered is not None:
            raise
        reader = _open_recovered(path, exc, wanted)
        collected = _read_topics(reader, source, joy_topic, twist_topic, truth_topic, axes,
                                 override_topic, base_frame, default_override)
    (jb, jr, jp, jd), (vb, vr, vp, vd), (tb, tr, tp, td), tw_conns, (ob, orows, op, od) = \
        collected
    digests = {topic: d for topic, d in ((joy_topic, jd), (twist_topic, vd),
                                         (truth_topic, td), (override_topic, od)) if topic and d}

    for name, topic, rows in (("joystick", joy_topic, jr), ("velocity", twist_topic, vr)):
        if not rows:
            raise BagError(f"{source}: {name} topic {topic!r} has no messages")
    j = np.asarray(jr, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vr, dtype=np.float64).reshape(-1, 4)
    has_header = tw_conns[0].msgtype != "geometry_msgs/msg/Twist"

    def stream(name: str, rows: list[tuple[Any, ...]], bag_ns: list[int], parts: list[int],
               header: bool = True) -> _Stream:
        return _Stream(name, np.asarray([r[0] for r in rows], dtype=np.int64) if header
                       else None, np.asarray(bag_ns, dtype=np.int64),
                       np.asarray(parts, dtype=np.int64))

    streams = [stream(joy_topic, jr, jb, jp), stream(twist_topic, vr, vb, vp, has_header)]
    if tr:
        streams.append(stream(truth_topic or "", tr, tb, tp))
    if orows:
        streams.append(stream(override_topic or "", orows, ob, op))
    timed = _stream_times(streams, max_stamp_skew, source)
    (joy_t, keep), (vel_t, keep_v) = timed[0], timed[1]
    joy_t, j = joy_t[keep], j[keep]
    vel_t, v = vel_t[keep_v], v[keep_v]
    for name, topic, rows in (("joystick", joy_topic, j), ("velocity", twist_topic, v)):
        if not rows.shape[0]:
            raise BagError(f"{source}: every message of the {name} topic {topic!r} is stale")
    truth_t = np.zeros(0)
    truth = np.zeros((0, 5))
    if tr:
        ta = np.asarray(tr, dtype=np.float64).reshape(-1, 6)
        truth_t, keep = timed[2]
        truth_t, truth = truth_t[keep], ta[keep, 1:]
    override_t = np.zeros(0)
    if orows:
        # an override is kept whatever its latency: it says the joystick did not drive
        override_t = timed[-1][0]
    for name, topic, bad, n in (
            ("joystick", joy_topic, int(np.count_nonzero(~joy_in_range(j[:, 1:]))), j.shape[0]),
            ("velocity", twist_topic, int(np.count_nonzero(~vel_in_range(v[:, 1:3]))),
             v.shape[0])):
        if bad:  # the resampler drops them; a large share means a wrong scale or topic
            log.warning("%s: %d of %d %s samples on %s are not finite or outside their "
                        "physical range (asgp_ros.core.streams); they are dropped", source,
                        bad, n, name, topic)
    try:
        return RawStreams(joy_t=joy_t, joy=j[:, 1:], vel_t=vel_t, vel=v[:, 1:3],
                          vel_ok=v[:, 3] > 0.5, truth_t=truth_t, truth=truth, source=source,
                          override_t=override_t, digests=digests)
    except ValueError as exc:
        raise BagError(f"{source}: {exc}") from exc


def bag_topics(path: str | os.PathLike[str]) -> dict[str, str]:
    """Topic name -> message type of a bag (of what a scan recovers, for a damaged one)."""
    reader = _open_reader(path, topics=())
    try:
        return {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


def read_sim_metadata(path: str | os.PathLike[str]) -> dict[str, Any] | None:
    """The simulator's description stored in a ROS 2 bag's metadata (None if absent).

    Raises:
        BagError: not a bag (see :func:`resolve_bag`), or metadata that does not parse
            (the description is JSON, read with
            :func:`asgp_ros.core.modelfile.loads_bounded`: size and nesting bounded).
    """
    bag = resolve_bag(path)
    if not bag.is_dir():
        return None
    meta_path = bag / "metadata.yaml"
    custom = _bag_metadata(bag).get("custom_data") or {}
    raw = custom.get(CUSTOM_DATA_KEY) if isinstance(custom, dict) else None
    if raw is None:
        return None
    try:
        if not isinstance(raw, str):
            raise TypeError(f"{CUSTOM_DATA_KEY} is not a JSON string")
        desc = loads_bounded(raw)
        if not isinstance(desc, dict):
            raise TypeError(f"{CUSTOM_DATA_KEY} is not a JSON object")
    except (ValueError, TypeError) as exc:
        raise BagError(f"{meta_path}: unreadable simulation description: "
                       f"{_one_line(exc)}") from exc
    return desc


# ----------------------------------------------------------------------------- recovery
# A recording that was killed (battery, SIGKILL, a full disk) leaves a bag without its
# index: an mcap file without its summary and footer, a ROS 1 bag whose index position is
# still 0, an SQLite file cut at a page, a directory without metadata.yaml. The scanners
# below read such files record by record from the start, keep every record that is
# complete, and stop at the first one that is not: a partial record is dropped, never
# decoded. What was lost is reported in a BagDamage.

MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\x00"
_STORAGE_SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3", ".bag": "ros1"}


class _StopError(Exception):
    """A record that cannot be parsed: the scan of this stream stops before it."""


@dataclass(frozen=True)
class RecoveredConnection:
    """A connection (topic and type) found by scanning a bag.

    Attributes:
        id: index in :attr:`RecoveredBag.connections`.
        topic, msgtype: as rosbags names them (``"sensor_msgs/msg/Joy"``).
        msgdef: the message definition stored in the bag ('' if none).
        encoding: its format: "ros2msg", "ros2idl" (ROS 2) or "msg" (ROS 1).
    """

    id: int
    topic: str
    msgtype: str
    msgdef: str = ""
    encoding: str = ""


@dataclass(frozen=True)
class BagDamage:
    """What a scan of a bag found, and what it could not recover.

    Attributes:
        bag: the bag. storage: "mcap", "sqlite3" or "ros1".
        file_bytes: size of the storage file(s).
        complete_bytes: bytes up to the end of the last complete record (SQLite: page).
        expected_bytes: the size the file says it had (SQLite header, ROS 1 index
            position), or None when unknown.
        messages: complete messages recovered; start_ns, end_ns: their bag-time range.
        dropped_messages: messages known to exist that were dropped (a partial record, a
            message of an unknown connection, a chunk whose checksum fails, an SQLite row
            whose page is missing).
        expected_messages, expected_end_ns: the count and end time a surviving index or
            metadata.yaml gives (None when unknown).
        intact: the storage ended as a complete bag ends (index, summary, footer) and no
            problem was found.
        problems: what was wrong, one phrase each.
    """

    bag: str
    storage: str
    file_bytes: int
    complete_bytes: int
    expected_bytes: int | None
    messages: int
    start_ns: int | None
    end_ns: int | None
    dropped_messages: int
    expected_messages: int | None
    expected_end_ns: int | None
    intact: bool
    problems: tuple[str, ...]

    @property
    def lost_bytes(self) -> int:
        """Bytes after the last complete record, plus those known to be missing."""
        tail = self.file_bytes - self.complete_bytes
        return tail + max(0, (self.expected_bytes or 0) - self.file_bytes)

    @property
    def lost_messages(self) -> int | None:
        """Messages lost, when a surviving index or metadata.yaml gives the count."""
        if self.expected_messages is None:
            return None
        return max(0, self.expected_messages - self.messages)

    def summary(self) -> str:
        """One line: what was recovered and what was lost."""
        if self.intact:
            return f"{self.bag}: intact ({self.storage}, {self.messages} messages)"
        span = (f" ({(self.end_ns - self.start_ns) * 1e-9:.3f} s of bag time, "
                f"{self.start_ns * 1e-9:.3f} .. {self.end_ns * 1e-9:.3f})"
                if self.start_ns is not None and self.end_ns is not None else "")
        parts = [f"{self.bag}: damaged {self.storage} bag ({'; '.join(self.problems)})",
                 f"recovered {self.messages} complete messages{span}"]
        lost = self.lost_messages
        if lost is not None:
            parts.append(f"lost {lost} of {self.expected_messages} messages")
        elif self.dropped_messages:
            parts.append(f"dropped {self.dropped_messages} incomplete or unreadable messages "
                         "(more may have been lost after the cut)")
        else:
            parts.append("how many messages followed the cut is unknown")
        if self.expected_end_ns is not None and self.end_ns is not None \
                and self.expected_end_ns > self.end_ns:
            parts.append(f"{(self.expected_end_ns - self.end_ns) * 1e-9:.3f} s lost at the end")
        tail = self.file_bytes - self.complete_bytes
        missing = max(0, (self.expected_bytes or 0) - self.file_bytes)
        parts.append(f"{tail} of {self.file_bytes} bytes after the last complete record"
                     + (f", {missing} bytes missing at the end" if missing else ""))
        return "; ".join(parts)


@dataclass
class RecoveredBag:
    """Everything a scan recovered from a bag (see :func:`recover_bag`).

    Attributes:
        connections: the connections, ``connections[i].id == i``.
        messages: (connection id, bag time ns, serialised message) in bag-time order
            (with ``record_order``, in the order they were written).
        ros1: the messages are ROS 1 serialised (else CDR).
        custom_data: a ROS 2 bag's custom metadata, when metadata.yaml survived.
        damage: what was found and lost.
    """

    connections: list[RecoveredConnection]
    messages: list[tuple[int, int, bytes]]
    ros1: bool
    custom_data: dict[str, str]
    damage: BagDamage


@dataclass
class _Scan:
    """What the scan of one storage file found (connection keys are per file)."""

    conns: dict[Any, tuple[str, str, str, str]] = field(default_factory=dict)
    messages: list[tuple[Any, int, bytes]] = field(default_factory=list)
    complete: int = 0
    expected_bytes: int | None = None
    expected_messages: int | None = None
    dropped: int = 0
    ended: bool = False
    problems: list[str] = field(default_factory=list)
    keep: Callable[[str], bool] = field(default=lambda _topic: True)

    def add(self, cid: Any, ns: int, data: Any) -> None:
        """A complete message; its bytes are copied only if its topic is wanted."""
        self.messages.append((cid, ns, bytes(data) if self.keep(self.conns[cid][0]) else b""))

    def drop_since(self, found: int, what: str) -> None:
        """Drop the messages added since there were ``found`` (a damaged chunk's: a record
        after the damage may be read from the wrong bytes), count them as dropped, and
        report ``what`` with their number."""
        lost = len(self.messages) - found
        del self.messages[found:]
        self.dropped += lost
        self.problems.append(f"{what} ({lost} messages dropped)")


def _u(buf: Any, pos: int, size: int, order: Literal["little", "big"] = "little") -> int:
    if pos < 0 or pos + size > len(buf):
        raise _StopError("past the end")
    return int.from_bytes(buf[pos:pos + size], order)


def _mcap_str(buf: Any, pos: int) -> tuple[str, int]:
    n = _u(buf, pos, 4)
    if pos + 4 + n > len(buf):
        raise _StopError("string past the end")
    try:
        return bytes(buf[pos + 4:pos + 4 + n]).decode("utf-8"), pos + 4 + n
    except UnicodeDecodeError as exc:
        raise _StopError("not UTF-8") from exc


def _decompress(data: bytes, compression: str, partial: bool) -> bytes:
    """A chunk's records; for a partial chunk, what its complete compressed blocks hold."""
    if compression in ("", "none"):
        return data
    try:
        if compression == "zstd":
            from backports import zstd

            return bytes(zstd.ZstdDecompressor().decompress(data)) if partial \
                else bytes(zstd.decompress(data))
        if compression == "lz4":
            import lz4.frame

            if partial:
                return bytes(lz4.frame.LZ4FrameDecompressor().decompress(data))
            return bytes(lz4.frame.decompress(data))
        if compression == "bz2":
            return bz2.BZ2Decompressor().decompress(data) if partial else bz2.decompress(data)
    except Exception as exc:  # each library raises its own error types
        raise _StopError(f"{compression} data do not decompress") from exc
    raise _StopError(f"unsupported compression {compression!r}")


def _scan_mcap(buf: Any, name: str, keep: Callable[[str], bool]) -> _Scan:
    """Scan an mcap file's data section record by record (no summary or index needed)."""
    scanner = _McapScanner(keep)
    scan = scanner.scan
    if bytes(buf[:8]) != MCAP_MAGIC:
        raise BagError(f"{name}: not an mcap file (it does not start with the mcap magic)")
    try:
        end, tail = scanner.records(buf, 8, nested=False)
    except _StopError as exc:
        scan.complete = scanner.progress
        scan.problems.append(f"unreadable record at byte {scanner.progress}: {exc}")
        return scan
    if not scan.ended:
        scan.complete = end
        scan.problems.append("the summary or footer is damaged (every message is before it)"
                             if scanner.data_end else
                             "no summary or footer (the recording did not finish)")
        if tail == 0x06:  # a chunk cut short: its complete records are good
            with contextlib.suppress(_StopError):
                scan.complete = scanner.chunk(buf[end + 9:], end, partial=True)
            scan.problems.append(f"the last chunk is cut at byte {len(buf)}")
        elif tail == 0x05:
            scan.dropped += 1
    return scan


class _McapScanner:
    """The state of one mcap scan: the schemas seen, the end of the last complete top-level
    record, whether the data section ended, and the time range of the current chunk."""

    def __init__(self, keep: Callable[[str], bool]) -> None:
        self.scan = _Scan(keep=keep)
        self.schemas: dict[int, tuple[str, str, str]] = {}
        self.progress = 8  # the end of the last complete top-level record
        self.data_end = False
        self.bounds = (0, 2**64)  # message times the current chunk's header allows

    def records(self, view: Any, pos: int, nested: bool) -> tuple[int, int | None]:
        """Handle the complete records from ``pos``; return the end of the last one and
        the opcode of a partial record after it (None: the view ended at a record)."""
        n = len(view)
        while pos < n:
            if n - pos < 9:
                return pos, -1
            op = view[pos]
            if op == 0x00:  # reserved: zeros where records should be (a sparse tail)
                raise _StopError(f"invalid opcode 0 at byte {pos}")
            end = pos + 9 + int.from_bytes(view[pos + 1:pos + 9], "little")
            if end > n:
                return pos, op
            body = view[pos + 9:end]
            if op == 0x03:  # Schema
                self._schema(body)
            elif op == 0x04:  # Channel
                self._channel(body)
            elif op == 0x05:  # Message
                self._message(body, nested)
            elif op == 0x06 and not nested:  # Chunk
                self.chunk(body, pos, partial=False)
            elif op == 0x0F and not nested:  # DataEnd: the summary follows
                self.data_end = True
                self.summary(view, end)
                return end, None
            elif nested and op not in (0x03, 0x04, 0x05):
                raise _StopError(f"record 0x{op:02x} inside a chunk")
            pos = end
            if not nested:
                self.progress = end
        return pos, None

    def _schema(self, body: Any) -> None:
        sid = _u(body, 0, 2)
        sname, p = _mcap_str(body, 2)
        enc, p = _mcap_str(body, p)
        ln = _u(body, p, 4)
        self.schemas[sid] = (sname, enc, bytes(body[p + 4:p + 4 + ln]).decode(
            "utf-8", "replace"))

    def _channel(self, body: Any) -> None:
        cid, sid = _u(body, 0, 2), _u(body, 2, 2)
        topic, _p = _mcap_str(body, 4)
        if sid in self.schemas:
            sname, enc, text = self.schemas[sid]
            self.scan.conns[cid] = (topic, sname, text, enc)

    def _message(self, body: Any, nested: bool) -> None:
        if len(body) < 22:
            raise _StopError("message record shorter than its header")
        cid, log_time = _u(body, 0, 2), _u(body, 6, 8)
        if nested and not self.bounds[0] <= log_time <= self.bounds[1]:
            raise _StopError("a message time outside its chunk's range")
        if cid in self.scan.conns:
            self.scan.add(cid, log_time, body[22:])
        else:
            self.scan.dropped += 1

    def chunk(self, body: Any, at: int, partial: bool) -> int:
        """Handle a chunk record's body; return the end of its last complete record in
        the file (uncompressed chunks) or ``at`` (compressed ones).

        Its records must lie in the chunk's time range and, for a complete chunk, fill it
        exactly; otherwise the chunk is damaged inside (a flipped length or time) and none
        of its messages is kept, since a record after the damage may be read from the
        wrong bytes."""
        scan = self.scan
        self.bounds = (_u(body, 0, 8), _u(body, 8, 8))
        size, crc = _u(body, 16, 8), _u(body, 24, 4)
        compression, p = _mcap_str(body, 28)
        stored = _u(body, p, 8)
        data = bytes(body[p + 8:p + 8 + stored])
        if not partial and len(data) != stored:
            raise _StopError("chunk shorter than its records")
        raw = _decompress(data, compression, partial)
        if not partial and (len(raw) != size or (crc and zlib.crc32(raw) != crc)):
            found = len(scan.messages)
            with contextlib.suppress(_StopError):
                self.records(raw, 0, nested=True)  # count what is lost, keep nothing
            scan.drop_since(found, f"chunk at byte {at} fails its checksum")
            return at
        found = len(scan.messages)
        try:
            inner, tail = self.records(memoryview(raw)[:size], 0, nested=True)
            if tail is not None and not partial:
                raise _StopError("it ends inside a record")
        except _StopError as exc:
            scan.drop_since(found, f"chunk at byte {at} is damaged inside: {exc}")
            return at
        if tail is not None:
            scan.dropped += 1 if tail in (-1, 0x05) else 0
        return at + 9 + p + 8 + inner if compression in ("", "none") else at

    def summary(self, view: Any, pos: int) -> None:
        """Read the summary section after DataEnd: the message count of its Statistics, and
        whether the file ends with a complete footer and the closing magic."""
        n = len(view)
        while pos + 9 <= n:
            op = view[pos]
            end = pos + 9 + int.from_bytes(view[pos + 1:pos + 9], "little")
            if end > n or op == 0x00:
                return
            if op == 0x0B:  # Statistics
                self.scan.expected_messages = _u(view, pos + 9, 8)
            if op == 0x02 and end + 8 == n and bytes(view[end:]) == MCAP_MAGIC:
                self.scan.ended = True
                self.scan.complete = n
                return
            pos = end


# --- SQLite: the database file is read page by page, never opened by sqlite itself (which
# would roll back a hot journal, i.e. drop the last transaction, and write to the bag).
def _varint(buf: Any, pos: int) -> tuple[int, int]:
    value = 0
    for k in range(9):
        if pos + k >= len(buf):
            raise _StopError("varint past the end")
        b = buf[pos + k]
        if k == 8:
            value = (value << 8) | b
            break
        value = (value << 7) | (b & 0x7F)
        if b < 0x80:
            break
    if value >= 1 << 63:
        value -= 1 << 64
    return value, pos + k + 1


def _sqlite_record(payload: bytes) -> list[Any]:
    """The values of an SQLite record (https://sqlite.org/fileformat.html#record_format)."""
    hlen, p = _varint(payload, 0)
    if not 0 < hlen <= len(payload):
        raise _StopError("record header size")
    types = []
    while p < hlen:
        t, p = _varint(payload, p)
        types.append(t)
    if p != hlen:
        raise _StopError("record header")
    pos = hlen
    values: list[Any] = []
    sizes = {1: 1, 2: 2, 3: 3, 4: 4, 5: 6, 6: 8}
    for t in types:
        if t == 0:
            values.append(None)
        elif t in sizes:
            n = sizes[t]
            values.append(int.from_bytes(payload[pos:pos + n], "big", signed=True))
            pos += n
        elif t == 7:
            if pos + 8 > len(payload):
                raise _StopError("record past its payload")
            values.append(struct.unpack(">d", payload[pos:pos + 8])[0])
            pos += 8
        elif t in (8, 9):
            values.append(t - 8)
        elif t >= 12:
            n = (t - 12) // 2
            chunk = payload[pos:pos + n]
            if t % 2:
                try:
                    values.append(chunk.decode("utf-8"))
                except UnicodeDecodeError as exc:
                    raise _StopError("text not UTF-8") from exc
            else:
                values.append(chunk)
            pos += n
        else:
            raise _StopError(f"serial type {t}")
        if pos > len(payload):
            raise _StopError("record past its payload")
    if pos != len(payload):
        raise _StopError("record size")
    return values


def _wal_pages(wal: bytes, page_size: int) -> tuple[dict[int, bytes], str | None]:
    """Pages of a write-ahead log whose frames pass their checksums, latest frame last.

    Frames are read while their salt and cumulative checksum hold
    (https://sqlite.org/fileformat.html#wal_file_format); a torn frame ends the log.
    """
    if len(wal) < 32:
        return {}, "empty write-ahead log" if wal else None
    magic, _ver, psize, _seq, salt1, salt2, c1, c2 = struct.unpack(">8I", wal[:32])
    if magic not in (0x377F0682, 0x377F0683) or psize != page_size:
        return {}, "write-ahead log with a bad header (ignored)"
    fmt = "<" if magic == 0x377F0682 else ">"

    def checksum(data: bytes, s0: int, s1: int) -> tuple[int, int]:
        words = struct.unpack(f"{fmt}{len(data) // 4}I", data)
        for i in range(0, len(words), 2):
            s0 = (s0 + words[i] + s1) & 0xFFFFFFFF
            s1 = (s1 + words[i + 1] + s0) & 0xFFFFFFFF
        return s0, s1

    s = checksum(wal[:24], 0, 0)
    if s != (c1, c2):
        return {}, "write-ahead log with a bad header checksum (ignored)"
    pages: dict[int, bytes] = {}
    pending: dict[int, bytes] = {}
    pos = 32
    while pos + 24 + page_size <= len(wal):
        pgno, commit, fs1, fs2, f1, f2 = struct.unpack(">6I", wal[pos:pos + 24])
        page = wal[pos + 24:pos + 24 + page_size]
        s = checksum(wal[pos:pos + 8] + page, *s)
        if (fs1, fs2) != (salt1, salt2) or s != (f1, f2):
            break
        pending[pgno] = page
        if commit:
            pages.update(pending)
            pending.clear()
        pos += 24 + page_size
    problem = None
    if pending:  # an append-only recorder's uncommitted pages hold complete rows too
        pages.update(pending)
        problem = "the write-ahead log ends inside a transaction"
    return pages, problem


def _scan_sqlite(path: Path, buf: Any, name: str, keep: Callable[[str], bool]) -> _Scan:
    """Scan a rosbag2 SQLite database page by page (a cut file has no tail pages)."""
    scan = _Scan(keep=keep)
    db = _SqlitePages(path, buf, name, scan)
    claimed = db.free_pages()  # pages on the free list may hold stale rows
    try:
        schema = db.rows(1, claimed)
    except _StopError as exc:
        raise BagError(f"{name}: unreadable SQLite schema: {exc}") from exc
    roots = {v[1]: v[3] for _r, v in schema if len(v) == 5 and v[0] == "table"
             and isinstance(v[3], int)}
    if "messages" not in roots or "topics" not in roots:
        raise BagError(f"{name}: not a rosbag2 database (no messages and topics tables)")
    tables = {t: db.rows(root, claimed) for t, root in roots.items() if t != "messages"}
    defs = {v[1]: (v[3], v[2]) for _r, v in tables.get("message_definitions", [])
            if len(v) >= 4 and isinstance(v[1], str) and isinstance(v[3], str)}
    for rowid, v in tables["topics"]:
        if len(v) >= 4 and all(isinstance(x, str) for x in v[1:4]):
            text, enc = defs.get(v[2], ("", ""))
            scan.conns[rowid] = (v[1], v[2], text, enc)
    found = db.message_rows(roots["messages"], claimed)
    for rowid in sorted(found):
        kept = found[rowid]
        if kept is None or kept[0] not in scan.conns:
            scan.dropped += 1
            continue
        scan.add(*kept)
    if found:  # ids are 1, 2, 3, ...: a gap below the largest found is a lost row
        scan.dropped += max(0, max(found) - len(found))
    ps, npages = db.page_size, db.npages
    scan.complete = min(len(buf) // ps, npages) * ps
    if len(buf) % ps and len(buf) // ps < npages:
        scan.problems.append(f"the file ends inside page {len(buf) // ps + 1}")
    if scan.expected_bytes is not None and scan.expected_bytes > len(buf):
        scan.problems.append(f"the file is cut: {(scan.expected_bytes - len(buf)) // ps} "
                             f"of {scan.expected_bytes // ps} pages missing at the end")
    scan.ended = not scan.problems and not scan.dropped
    return scan


_ROWIDS = (-(1 << 63) - 1, (1 << 63) - 1)  # (lo, hi]: every rowid


def _merged(ranges: list[tuple[int, int]]) -> tuple[list[int], list[int]]:
    """Key ranges (lo, hi] merged where they overlap: their starts and ends, in order."""
    starts: list[int] = []
    ends: list[int] = []
    for lo, hi in sorted(ranges):
        if starts and lo <= ends[-1]:
            ends[-1] = max(ends[-1], hi)
        else:
            starts.append(lo)
            ends.append(hi)
    return starts, ends


class _SqlitePages:
    """The pages of one SQLite database file, with the valid pages of its write-ahead log
    over them (https://sqlite.org/fileformat.html); what is wrong goes to ``scan``."""

    def __init__(self, path: Path, buf: Any, name: str, scan: _Scan) -> None:
        """Read the header (page size, size in pages), the write-ahead log and whether a
        rollback journal was left; BagError if the file is not an SQLite database."""
        if len(buf) < 100 or bytes(buf[:16]) != SQLITE_MAGIC:
            raise BagError(f"{name}: not an SQLite database (no SQLite header)")
        ps = _u(buf, 16, 2, "big")
        ps = 65536 if ps == 1 else ps
        if ps < 512 or ps & (ps - 1):
            raise BagError(f"{name}: SQLite header with a bad page size {ps}")
        self.buf, self.scan, self.page_size = buf, scan, ps
        self.usable = ps - buf[20]
        self.npages = len(buf) // ps
        if _u(buf, 24, 4, "big") == _u(buf, 92, 4, "big") and _u(buf, 28, 4, "big"):
            scan.expected_bytes = _u(buf, 28, 4, "big") * ps
            if self.npages > scan.expected_bytes // ps:  # bytes after the database
                scan.problems.append(f"{len(buf) - scan.expected_bytes} bytes after the end "
                                     "of the database")
                self.npages = scan.expected_bytes // ps
        self.overlay: dict[int, bytes] = {}
        wal_path = path.with_name(path.name + "-wal")
        if regular_file_problem(wal_path) is None:
            self.overlay, problem = _wal_pages(wal_path.read_bytes(), ps)
            if problem:
                scan.problems.append(problem)
            if self.overlay.pop(0, None) is not None:
                scan.problems.append("a write-ahead log frame for page 0 (ignored)")
            if self.overlay:
                self.npages = max(self.npages, max(self.overlay))
                scan.expected_bytes = None  # the log holds the newest size
        if regular_file_problem(path.with_name(path.name + "-journal")) is None:
            scan.problems.append("a rollback journal was left (the last transaction did not "
                                 "finish); the database is read as it was written")
        # overflow pages read, in all: each is read once in a sound file; chains that share
        # pages would read the file again for each cell
        self.overflow_budget = 4 * self.npages + 64
        self.free_whole = True  # the free list was read to its end

    def report(self, problem: str) -> None:
        """Add ``problem`` to the scan's problems once."""
        if problem not in self.scan.problems:
            self.scan.problems.append(problem)

    def page(self, p: int) -> bytes | None:
        """Page ``p`` (1-based), None where it is missing."""
        if p in self.overlay:
            return self.overlay[p]
        ps = self.page_size
        if 1 <= p <= self.npages and p * ps <= len(self.buf):
            return bytes(self.buf[(p - 1) * ps:p * ps])
        return None

    def present(self) -> list[int]:
        """The numbers of the pages that are present, in order (not 1..npages: a log
        frame may name a page far beyond the file)."""
        in_file = range(1, min(self.npages, len(self.buf) // self.page_size) + 1)
        return sorted(set(in_file) | {p for p in self.overlay if p <= self.npages})

    def kind(self, p: int) -> int:
        """The b-tree page type of page ``p`` (0x0D table leaf, 0x05 table interior), -1
        where the page is missing."""
        pg = self.page(p)
        return -1 if pg is None else pg[100 if p == 1 else 0]

    def cells(self, p: int) -> tuple[list[tuple[int, bytes | None]], int]:
        """(rowid, payload or None if its overflow pages are missing or broken) of each
        readable cell of a table leaf, and the number of cells that cannot be read (a
        pointer, size or rowid that runs past the page)."""
        pg = self.page(p)
        assert pg is not None
        h = 100 if p == 1 else 0
        out: list[tuple[int, bytes | None]] = []
        bad = 0
        for i in range(_u(pg, h + 3, 2, "big")):
            try:
                out.append(self._cell(pg, _u(pg, h + 8 + 2 * i, 2, "big")))
            except _StopError:
                bad += 1
                if h + 10 + 2 * i > self.usable:  # the pointer array itself runs out
                    bad += _u(pg, h + 3, 2, "big") - i - 1
                    break
        return out, bad

    def _cell(self, pg: bytes, c: int) -> tuple[int, bytes | None]:
        """(rowid, payload) of the table leaf cell at offset ``c`` of page ``pg``."""
        usable = self.usable
        if not 0 < c < usable:
            raise _StopError("cell outside its page")
        size, c = _varint(pg, c)
        rowid, c = _varint(pg, c)
        x = usable - 35
        if size < 0 or c > usable:
            raise _StopError("cell past its page")
        if size <= x:
            if c + size > usable:
                raise _StopError("cell past its page")
            return rowid, pg[c:c + size]
        m = ((usable - 12) * 32 // 255) - 23
        local = m + (size - m) % (usable - 4)
        local = local if local <= x else m
        if c + local + 4 > usable:
            raise _StopError("cell past its page")
        if size > local + self.npages * (usable - 4):
            return rowid, None  # more overflow pages than the file has
        data = [pg[c:c + local]]
        have, nxt, chain = local, _u(pg, c + local, 4, "big"), set()
        while have < size and nxt and nxt not in chain and self.overflow_budget > 0:
            ov = self.page(nxt)
            if ov is None:
                break
            chain.add(nxt)
            self.overflow_budget -= 1
            take = min(size - have, usable - 4)
            data.append(ov[4:4 + take])
            have, nxt = have + take, _u(ov, 0, 4, "big")
        if have < size and self.overflow_budget <= 0:
            self.report("overflow pages read more than four times over (shared overflow "
                        "chains); the rest dropped")
        if have == size and nxt == 0:
            return rowid, b"".join(data)
        if nxt in chain or have == size:  # a loop, or a chain that goes on: wrong bytes
            self.report("an overflow chain that loops or runs past its payload")
        return rowid, None

    def interior(self, p: int, lo: int, hi: int) -> tuple[list[tuple[int, int, int]],
                                                          list[tuple[int, int]]]:
        """The children of table interior page ``p`` whose keys are in (lo, hi]: (child,
        lo, hi) each, and the key ranges whose child pointer cannot be read."""
        pg = self.page(p)
        assert pg is not None
        h = 100 if p == 1 else 0
        children: list[tuple[int, int, int]] = []
        lost: list[tuple[int, int]] = []
        prev, broken = lo, False
        try:
            n = _u(pg, h + 3, 2, "big")
        except _StopError:
            return [], [(lo, hi)]
        for i in range(n):
            try:
                c = _u(pg, h + 12 + 2 * i, 2, "big")
                if not 0 < c <= self.usable - 5:
                    raise _StopError("cell outside its page")
                child = _u(pg, c, 4, "big")
                key, end = _varint(pg, c + 4)
                if end > self.usable:
                    raise _StopError("cell past its page")
            except _StopError:
                broken = True
                continue
            key = min(max(key, prev), hi)
            if broken:
                lost.append((prev, key))
                broken = False
            children.append((child, prev, key))
            prev = key
        if broken:
            lost.append((prev, hi))
        if lost:
            self.report(f"unreadable cells on interior page {p}")
        children.append((_u(pg, h + 8, 4, "big"), prev, hi))
        return children, lost

    def tree(self, root: int, seen: set[int]) -> tuple[list[int], list[tuple[int, int]]]:
        """The table leaf pages reached from ``root`` and the key ranges (lo, hi] of the
        subtrees that cannot be reached (a missing page, a pointer to a page seen before
        or to a page that is not a table page); the pages walked are added to ``seen``."""
        found: list[int] = []
        lost: list[tuple[int, int]] = []
        # pages past the file's end but within the header's size are the cut's, not bad
        # pointers (the cut itself is reported once, by _scan_sqlite)
        limit = self.npages
        if self.scan.expected_bytes is not None:
            limit = max(limit, self.scan.expected_bytes // self.page_size)
        stack = [(root, *_ROWIDS)]
        while stack:
            p, lo, hi = stack.pop()
            k = self.kind(p) if p not in seen else -1
            if k not in (0x05, 0x0D):
                if lo < hi:
                    lost.append((lo, hi))
                if self.page(p) is not None or not 0 < p <= limit:  # not a cut page
                    self.report("a b-tree pointer to a page that is not one of its table's")
                continue
            seen.add(p)
            if k == 0x0D:
                found.append(p)
                continue
            children, broken = self.interior(p, lo, hi)
            lost.extend(broken)
            stack.extend(reversed(children))
        return found, lost

    def leaves(self, root: int, seen: set[int]) -> list[int]:
        """Table leaf pages reached from ``root`` (missing pages are skipped)."""
        return self.tree(root, seen)[0]

    def rows(self, root: int, seen: set[int]) -> list[tuple[int, list[Any]]]:
        """(rowid, values) of the table whose b-tree starts at page ``root``; its pages are
        added to ``seen``, an unreadable cell is reported and skipped."""
        out: list[tuple[int, list[Any]]] = []
        for p in self.leaves(root, seen):
            for r, d in self.leaf_rows(p):
                if d is not None:
                    out.append((r, d))
        return out

    def leaf_rows(self, p: int) -> list[tuple[int, list[Any] | None]]:
        """(rowid, values, or None where its overflow pages are missing or broken) of the
        readable cells of table leaf ``p``; what cannot be read is reported."""
        cells, bad = self.cells(p)
        out: list[tuple[int, list[Any] | None]] = []
        for r, d in cells:
            try:
                out.append((r, None if d is None else _sqlite_record(d)))
            except _StopError:
                bad += 1
        if bad:
            self.scan.problems.append(f"{bad} unreadable cell{'s' * (bad > 1)} on page {p}")
        return out

    def free_pages(self) -> set[int]:
        """The pages of the free list (trunk and leaf pages), as far as they can be read;
        the list starts in page 1's header, which a write-ahead log may hold newer."""
        first = self.page(1)
        if first is None:
            return set()
        usable = self.usable
        free: set[int] = set()
        trunks: set[int] = set()
        trunk = _u(first, 32, 4, "big")
        broken = False
        while trunk and trunk not in trunks and (pg := self.page(trunk)) is not None:
            trunks.add(trunk)
            free.add(trunk)
            n = _u(pg, 4, 4, "big")
            broken |= n > usable // 4 - 2  # more leaves than a trunk page holds
            free.update(_u(pg, 8 + 4 * i, 4, "big") for i in range(min(n, usable // 4 - 2)))
            trunk = _u(pg, 0, 4, "big")
        if trunk or broken or len(free) < _u(first, 36, 4, "big"):
            self.free_whole = False
            self.report("the free list is cut off or broken: pages outside the messages "
                        "table's b-tree are not read (they may hold deleted rows)")
        return free

    def message_rows(self, root: int, claimed: set[int]
                     ) -> dict[int, tuple[int, int, bytes] | None]:
        """The rows of the messages table by rowid: (topic id, time, data), or None where
        two different versions of a row were found or its overflow pages are missing.

        The leaves of the table's b-tree are read; then, if the free list was read whole,
        every other table leaf not claimed by another table or the free list (a cut file
        may have lost the interior pages that lead to them) when all its rows have the
        messages table's shape, for the rows whose ids lie where the b-tree has lost a
        subtree: a stale page (rows deleted) or a stray page of another table gives none of
        its rows where the b-tree is whole. Rows on free pages never come back: they were
        deleted, or are older versions of rows."""
        leaves, lost = self.tree(root, set(claimed))
        found: dict[int, tuple[int, int, bytes] | None] = {}
        in_tree = set(leaves)
        for p in leaves:
            for r, w in self.leaf_rows(p):
                self._put(found, r, w)
        tree_rows = set(found)
        starts, ends = _merged(lost)
        for p in self.present() if self.free_whole else ():
            if p in claimed or p in in_tree or self.kind(p) != 0x0D:
                continue
            page_rows = self.leaf_rows(p)
            if not all(w is None or (len(w) == 4 and w[0] is None and isinstance(w[1], int)
                                     and isinstance(w[2], int) and isinstance(w[3], bytes))
                       for _r, w in page_rows):
                continue  # another table's page
            for r, w in page_rows:
                i = bisect.bisect_left(starts, r) - 1
                if r not in tree_rows and i >= 0 and r <= ends[i]:
                    self._put(found, r, w)
        return found

    @staticmethod
    def _put(found: dict[int, tuple[int, int, bytes] | None], r: int,
             w: list[Any] | None) -> None:
        if w is not None and not (len(w) == 4 and isinstance(w[1], int)
                                  and isinstance(w[2], int) and isinstance(w[3], bytes)):
            w = None  # not a message row
        row = None if w is None else (w[1], w[2], w[3])
        if r in found and found[r] != row:
            found[r] = None  # two different versions of one row: trust neither
        else:
            found[r] = row


# --- ROS 1: records (header, data) from the version line on; chunks hold the messages.
def _ros1_header(buf: Any) -> dict[str, bytes]:
    fields, pos = {}, 0
    while pos < len(buf):
        n = _u(buf, pos, 4)
        if pos + 4 + n > len(buf):
            raise _StopError("header field past the end")
        name, sep, value = bytes(buf[pos + 4:pos + 4 + n]).partition(b"=")
        if not sep:
            raise _StopError("header field without '='")
        fields[name.decode("ascii", "replace")] = value
        pos += 4 + n
    return fields


def _ros1_type(name: str) -> str:
    parts = name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else name


def _scan_ros1(buf: Any, name: str, keep: Callable[[str], bool]) -> _Scan:
    """Scan a ROS 1 bag record by record from its version line (no index needed)."""
    scanner = _Ros1Scanner(keep)
    scan = scanner.scan
    if bytes(buf[:len(ROS1_MAGIC)]) != ROS1_MAGIC:
        raise BagError(f"{name}: not a ROS 1 bag (version 2.0): it does not start with "
                       "'#ROSBAG V2.0'")
    try:
        end, tail = scanner.records(buf, len(ROS1_MAGIC), nested=False)
    except _StopError as exc:
        # what follows the last complete record is no record: the file is cut there (a
        # recorder's preallocated zeros), or it has garbage after a complete index
        scan.complete = scanner.top_end
        if scanner.index_pos and scanner.expected_chunks:
            scan.expected_bytes = scanner.index_pos
        scan.problems.append(
            f"{len(buf) - scanner.top_end} bytes after the index are no record ({exc}); "
            "every message is before them"
            if scanner.index_pos and scanner.top_end > scanner.index_pos
            else f"unreadable record: {exc}")
        return scan
    index_pos, chunks, expected_chunks = (scanner.index_pos, scanner.chunks,
                                          scanner.expected_chunks)
    scan.complete = end
    if index_pos and expected_chunks:
        scan.expected_bytes = index_pos
    if tail is not None and tail[0].get("op", b"")[:1] == b"\x05":
        with contextlib.suppress(_StopError):
            scan.complete = tail[1] + scanner.chunk(tail[0], buf[tail[1]:], end,
                                                    partial=True) or end
        scan.problems.append(f"the last chunk is cut at byte {len(buf)}")
    elif end < len(buf):
        scan.problems.append("the index is cut (every message is before it)"
                             if index_pos and end >= index_pos else
                             f"the file ends inside a record at byte {end}")
    if not index_pos:
        scan.problems.append("no index (the recording did not finish)")
    elif len(buf) < index_pos:
        scan.problems.append(f"cut at byte {len(buf)} before the index at byte {index_pos}; "
                             f"{chunks} of {expected_chunks} chunks complete")
    scan.ended = not scan.problems and index_pos > 0
    return scan


class _Ros1Scanner:
    """The state of one ROS 1 scan: where the bag header says the index is, and the chunks
    it announces and those found complete."""

    def __init__(self, keep: Callable[[str], bool]) -> None:
        self.scan = _Scan(keep=keep)
        self.index_pos = 0
        self.chunks = 0
        self.expected_chunks = 0
        self.top_end = len(ROS1_MAGIC)  # the end of the last complete top-level record

    def records(self, view: Any, pos: int, nested: bool
                ) -> tuple[int, tuple[dict[str, bytes], int] | None]:
        """Handle the complete records from ``pos``; return the end of the last one and,
        for a partial record after it, its header and data position."""
        n = len(view)
        while pos < n:
            if n - pos < 4:
                return pos, None
            hlen = _u(view, pos, 4)
            if hlen < 8:  # not even an op field: zeros where records should be
                raise _StopError(f"record header of {hlen} bytes at byte {pos}")
            if pos + 4 + hlen + 4 > n:
                return pos, None
            head = _ros1_header(view[pos + 4:pos + 4 + hlen])
            dpos = pos + 8 + hlen
            end = dpos + _u(view, pos + 4 + hlen, 4)
            if end > n:
                return pos, (head, dpos)
            op = head.get("op", b"\xff")[:1]
            data = view[dpos:end]
            if op == b"\x03" and not nested:  # bag header
                self.index_pos = _u(head.get("index_pos", b""), 0, 8)
                self.expected_chunks = _u(head.get("chunk_count", b""), 0, 4)
            elif op == b"\x05" and not nested:  # chunk
                self.chunk(head, data, pos, partial=False)
                self.chunks += 1
            elif op == b"\x07":  # connection
                self._connection(head, data)
            elif op == b"\x02":  # message data
                self._message(head, data)
            elif nested:
                raise _StopError(f"record op {op!r} inside a chunk")
            pos = end
            if not nested:
                self.top_end = end
        return pos, None

    def _connection(self, head: dict[str, bytes], data: Any) -> None:
        cid = _u(head.get("conn", b""), 0, 4)
        info = _ros1_header(data)
        topic = head.get("topic", b"").decode("utf-8", "replace")
        typ = info.get("type", b"").decode("utf-8", "replace")
        text = info.get("message_definition", b"").decode("utf-8", "replace")
        self.scan.conns[cid] = (topic, _ros1_type(typ), text, "msg")

    def _message(self, head: dict[str, bytes], data: Any) -> None:
        cid = _u(head.get("conn", b""), 0, 4)
        t = head.get("time", b"")
        ns = _u(t, 0, 4) * 1_000_000_000 + _u(t, 4, 4)
        if cid in self.scan.conns:
            self.scan.add(cid, ns, data)
        else:
            self.scan.dropped += 1

    def chunk(self, head: dict[str, bytes], data: Any, at: int, partial: bool) -> int:
        """Handle a chunk; return the end of its last complete record in the data
        (uncompressed chunks) or 0 (compressed ones)."""
        scan = self.scan
        compression = head.get("compression", b"none").decode("ascii", "replace")
        raw = _decompress(bytes(data), compression, partial)
        size = _u(head.get("size", b""), 0, 4)
        if not partial and len(raw) != size:
            raise _StopError(f"chunk at byte {at} has {len(raw)} bytes, not {size}")
        found = len(scan.messages)
        try:  # a complete chunk must be filled exactly by its records (as in _scan_mcap)
            inner, tail = self.records(memoryview(raw)[:size], 0, nested=True)
            if not partial and (tail is not None or inner != size):
                raise _StopError("it ends inside a record")
        except _StopError as exc:
            scan.drop_since(found, f"chunk at byte {at} is damaged inside: {exc}")
            return 0
        if tail is not None:
            scan.dropped += 1 if tail[0].get("op") == b"\x02" else 0
        return inner if compression == "none" else 0


def _split_order(name: str) -> tuple[object, ...]:
    """A storage file's name as a key that orders a split recording's files by their
    numbers (``bag_2`` before ``bag_10``: sorted as text, the eleventh file of a killed
    recording was read before the third, a step back of the clock)."""
    return tuple((0, int(part), "") if part.isdigit() else (1, 0, part)
                 for part in re.split(r"(\d+)", name))


def _storage_files(path: str | os.PathLike[str], listed_only: bool = False
                   ) -> tuple[Path, str, list[Path], list[str]]:
    """The bag, its storage kind, its storage files and the problems of their listing (a
    file metadata.yaml names that is not there, one there that it does not name), for a
    scan.

    Accepts what :func:`resolve_bag` accepts, and also a ROS 2 bag directory whose
    metadata.yaml is missing or unreadable (the recorder writes it last), or a lone
    ``.mcap`` / ``.db3`` file. Every file is checked to be a regular file before it is
    opened. ``listed_only``: of a bag whose metadata.yaml lists its files, those alone (what
    an indexed reader reads; a stray storage file beside them is another recording).
    """
    p = Path(path)
    mode = _bag_mode(p)
    if not stat.S_ISDIR(mode):
        problem = file_type_problem(mode)
        if problem is not None:
            raise BagError(f"{p}: {problem}: a bag is a ROS 1 .bag file or a ROS 2 bag "
                           "directory")
        if p.suffix not in _STORAGE_SUFFIXES:
            raise BagError(f"{p}: not a bag: expected a ROS 1 .bag file, a ROS 2 bag "
                           "directory or its .mcap / .db3 file")
        if p.suffix == ".bag":
            return p, "ros1", [p], []
        if regular_file_problem(p.parent / "metadata.yaml") is None:
            p = p.parent if str(p.parent) else Path(".")
        else:
            return p, _STORAGE_SUFFIXES[p.suffix], [p], []
    names: list[str] = []
    try:
        files = _bag_metadata(p).get("relative_file_paths")
        if isinstance(files, list) and all(isinstance(f, str) for f in files):
            names = [f for f in files if "/" not in f and f not in ("", ".", "..")]
    except BagError:
        pass
    try:
        present = sorted((e.name for e in os.scandir(p)
                          if Path(e.name).suffix in (".mcap", ".db3")), key=_split_order)
    except OSError as exc:
        raise BagError(f"{p}: cannot list the bag directory: {exc.strerror}") from exc
    # the files metadata.yaml names, then any other (a split the metadata never listed)
    ordered = [n for n in names if n in present] + [
        n for n in present if n not in names and not (listed_only and names)]
    kinds = {_STORAGE_SUFFIXES[Path(n).suffix] for n in ordered}
    if not ordered:
        raise BagError(f"{p}: not a ROS 2 bag (no metadata.yaml and no .mcap or .db3 "
                       "file)" if not names else f"{p}: no storage file of the bag is left")
    if len(kinds) > 1:
        raise BagError(f"{p}: both .mcap and .db3 files; cannot tell which is the bag")
    for n in ordered:
        problem = regular_file_problem(p / n)
        if problem is not None:
            raise BagError(f"{p / n}: {problem} (a storage file of the bag {p})")
    listing = [f"{n} (listed in metadata.yaml) is missing" for n in names if n not in present]
    if names:
        listing += [f"{n} is not listed in metadata.yaml (read too)" for n in present
                    if n not in names]
    return p, kinds.pop(), [p / n for n in ordered], listing


def recover_bag(path: str | os.PathLike[str],
                topics: Collection[str] | None = None, *,
                record_order: bool = False, listed_only: bool = False) -> RecoveredBag:
    """Every complete message of a bag, read without its index (for a damaged bag).

    mcap: the records of the data section in order (a cut chunk gives its complete
    records); SQLite (.db3): the database pages (rows whose pages are missing are lost;
    a write-ahead log's valid frames are applied); ROS 1: the records in order (a cut chunk
    gives its complete records). A partial record is dropped, never decoded. Nothing is
    written: the bag is opened read-only.

    Args:
        path: the bag (as for :func:`resolve_bag`, or a directory or storage file without
            metadata.yaml).
        topics: keep the bytes of these topics' messages only (the others are listed with
            their times and empty data, so that a camera bag is not held in memory); None
            keeps everything.
        record_order: the messages in the order they were written (the storage files in
            their order, each file's records in theirs), not sorted by bag time.
        listed_only: of a bag whose metadata.yaml lists its storage files, those alone.

    Raises:
        BagError: not a bag, or nothing recoverable (no connection found).
    """
    bag, storage, files, listing = _storage_files(path, listed_only)
    wanted = None if topics is None else frozenset(topics)

    def keep(topic: str) -> bool:
        return wanted is None or topic in wanted

    custom, expected_messages, expected_end, problems = _metadata_expectations(bag)
    problems += listing
    scans: list[_Scan] = []
    size = 0
    for f in files:
        scan, n = _scan_storage_file(f, storage, keep, only=len(files) == 1)
        scans.append(scan)
        size += n
    connections, messages, repeated = _merge_scans(scans)
    if repeated:
        problems.append(f"{repeated} messages of one storage file repeat another's (a copy "
                        "of it in the bag): kept once")
    if not connections:
        found = "; ".join(problems + [p for s in scans for p in s.problems]) or "no data"
        raise BagError(f"{bag}: nothing recoverable: no complete connection record ({found})")
    if not record_order:
        messages.sort(key=lambda m: m[1])  # stable: file order within one time
    times = [m[1] for m in messages]
    n_expected = (expected_messages if expected_messages is not None
                  else sum(s.expected_messages or 0 for s in scans) or None)
    all_problems = tuple(problems + [p for s in scans for p in s.problems])
    if not all_problems and expected_messages is not None \
            and expected_messages != len(messages):
        # every file ended as a bag ends, yet they do not hold what metadata.yaml counts
        all_problems = (f"{len(messages)} messages where metadata.yaml counts "
                        f"{expected_messages}",)
    exp_bytes = (sum(s.expected_bytes or 0 for s in scans)
                 if all(s.expected_bytes is not None for s in scans) else None)
    damage = BagDamage(
        bag=str(bag), storage=storage, file_bytes=size,
        complete_bytes=sum(s.complete for s in scans), expected_bytes=exp_bytes,
        messages=len(messages), start_ns=min(times) if times else None,
        end_ns=max(times) if times else None,
        dropped_messages=sum(s.dropped for s in scans), expected_messages=n_expected,
        expected_end_ns=expected_end,
        intact=all(s.ended for s in scans) and not all_problems,
        problems=all_problems)
    return RecoveredBag(connections, messages, storage == "ros1", custom, damage)


def _count_in_range(value: object, limit: int = 1 << 53) -> TypeGuard[int]:
    """A count (or nanoseconds) from metadata.yaml that can be one: an int, not a bool,
    in [0, limit); anything else is no expectation at all."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < limit


def _metadata_expectations(bag: Path) -> tuple[dict[str, str], int | None, int | None,
                                                list[str]]:
    """What a ROS 2 bag's metadata.yaml says, if it survived: (custom data, message count,
    end time in ns, problems found); nothing for a ROS 1 bag or a lone storage file."""
    custom: dict[str, str] = {}
    expected_messages = expected_end = None
    problems: list[str] = []
    if bag.is_dir():
        try:
            info = _bag_metadata(bag)
            c = info.get("custom_data")
            custom = {k: v for k, v in c.items() if isinstance(k, str)
                      and isinstance(v, str)} if isinstance(c, dict) else {}
            mc, st, du = (info.get("message_count"), info.get("starting_time"),
                          info.get("duration"))
            expected_messages = mc if _count_in_range(mc) else None
            if isinstance(st, dict) and isinstance(du, dict):
                start = st.get("nanoseconds_since_epoch")
                dur = du.get("nanoseconds")
                if _count_in_range(start, 1 << 63) and _count_in_range(dur, 1 << 63) \
                        and start + dur < 1 << 63:
                    expected_end = start + dur
        except BagError as exc:
            what = "missing" if "without" in str(exc) else "unreadable"
            problems.append(f"metadata.yaml {what}")
    return custom, expected_messages, expected_end, problems


def _scan_storage_file(f: Path, storage: str, keep: Callable[[str], bool], *, only: bool
                       ) -> tuple[_Scan, int]:
    """The scan of one storage file, memory-mapped read-only (not read into memory), and
    its size; ``only``: the bag's one storage file (its emptiness is then the bag's)."""
    with open(f, "rb") as fh:
        n = os.fstat(fh.fileno()).st_size
        if n == 0:
            raise BagError(f"{f}: empty file: nothing to recover") if only \
                else BagError(f"{f}: empty storage file")
        try:
            mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)  # not read in memory
        except (OSError, ValueError, OverflowError) as exc:
            raise BagError(f"{f}: cannot be mapped for a scan: {_one_line(exc)}") from exc
        try:
            if storage == "mcap":
                return _scan_mcap(memoryview(mm), str(f), keep), n
            if storage == "sqlite3":
                return _scan_sqlite(f, mm, str(f), keep), n
            return _scan_ros1(memoryview(mm), str(f), keep), n
        finally:
            with contextlib.suppress(BufferError):  # a view still held: closed when freed
                mm.close()


def _merge_scans(scans: list[_Scan]) -> tuple[list[RecoveredConnection],
                                              list[tuple[int, int, bytes]], int]:
    """The connections of all the storage files, one per (topic, type) in order of first
    appearance, every message with its connection renumbered (in file order), and how many
    messages were left out as repeating, in topic, time and bytes, one of an earlier file
    (a stray copy of a storage file in the bag: every message twice, the output "intact")."""
    connections: list[RecoveredConnection] = []
    ids: dict[tuple[str, str], int] = {}
    messages: list[tuple[int, int, bytes]] = []
    seen: set[tuple[int, int, bytes]] = set()
    repeated = 0
    for n, scan in enumerate(scans):
        local: dict[Any, int] = {}
        for key, (topic, msgtype, text, enc) in scan.conns.items():
            if (topic, msgtype) not in ids:
                ids[(topic, msgtype)] = len(connections)
                connections.append(RecoveredConnection(len(connections), topic, msgtype,
                                                       text, enc))
            local[key] = ids[(topic, msgtype)]
        mine = [(local[c], ns, data) for c, ns, data in scan.messages]
        if n:  # within one file, repeats are the recording's own
            kept = [m for m in mine if m not in seen]
            repeated += len(mine) - len(kept)
            mine = kept
        if len(scans) > 1:
            seen.update(mine)
        messages.extend(mine)
    return connections, messages, repeated


class _RecoveredReader:
    """The part of rosbags' AnyReader that :func:`read_streams` uses, over a scan in record
    order (:func:`recover_bag`). The messages come in bag-time order, unless the recorder's
    clock stepped back during the recording (:func:`clock_parts`): then in the order they
    were written, and :meth:`message_parts` tells each one's part."""

    def __init__(self, recovered: RecoveredBag, typestore: Any) -> None:
        self.recovered = recovered
        self.connections = recovered.connections
        self.typestore = _typestore_for(recovered, typestore)
        times = [m[1] for m in recovered.messages]
        self.parts = message_parts(recovered.messages)
        if self.parts.size and self.parts[-1]:
            log.warning("%s: %s: sorted by time its %d parts would interleave; they are "
                        "read one after another, each on its own times",
                        recovered.damage.bag, clock_steps_text(times, self.parts),
                        int(self.parts[-1]) + 1)
        else:
            recovered.messages.sort(key=lambda m: m[1])  # stable: file order within a time

    def messages(self, connections: Sequence[RecoveredConnection]
                 ) -> Any:
        wanted = {c.id for c in connections}
        for cid, ns, data in self.recovered.messages:
            if cid in wanted:
                yield self.connections[cid], ns, data

    def message_parts(self, connections: Sequence[RecoveredConnection]) -> Any:
        """The parts of the messages :meth:`messages` gives for ``connections``, in order."""
        wanted = {c.id for c in connections}
        for (cid, _ns, _data), part in zip(self.recovered.messages, self.parts, strict=True):
            if cid in wanted:
                yield int(part)

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        if self.recovered.ros1:
            return self.typestore.deserialize_ros1(raw, msgtype)
        return self.typestore.deserialize_cdr(raw, msgtype)

    def close(self) -> None:
        pass


def _typestore_for(recovered: RecoveredBag, typestore: Any) -> Any:
    """``typestore`` with the bag's own definitions of the types it does not know."""
    from rosbags.typesys import get_types_from_idl, get_types_from_msg

    for c in recovered.connections:
        if c.msgtype in typestore.types or not c.msgdef:
            continue
        try:
            types = (get_types_from_idl(c.msgdef) if c.encoding == "ros2idl"
                     else get_types_from_msg(c.msgdef, c.msgtype))
            typestore.register(types)
        except Exception as exc:  # a definition rosbags cannot parse: that type is unread
            log.warning("%s: cannot use the bag's definition of %s: %s",
                        recovered.damage.bag, c.msgtype, _one_line(exc))
    return typestore


def _open_recovered(path: str | os.PathLike[str], why: BagError,
                    topics: Collection[str] | None = None) -> _RecoveredReader:
    """A reader over what a scan of a damaged bag recovered (the messages of ``topics``),
    with a warning; ``why`` (the error of the normal reader) if nothing is recoverable."""
    from rosbags.typesys import Stores, get_typestore

    try:
        recovered = recover_bag(path, topics, record_order=True)
    except BagError as exc:
        raise BagError(f"{why}; {exc}" if str(exc) not in str(why) else str(why)) from exc
    damage = recovered.damage
    if damage.intact:  # the storage is whole; what failed is around it (its metadata.yaml)
        log.warning("%s; its storage is intact (%s, %d messages): read from a scan of it; "
                    "`asgp bag repair` writes a clean copy", why, damage.storage,
                    damage.messages)
    else:
        log.warning("%s", damage.summary())
        log.warning("%s: read from a scan of the damaged bag; `asgp bag repair` writes a "
                    "clean copy", damage.bag)
    store = get_typestore(Stores.ROS1_NOETIC if recovered.ros1 else Stores.ROS2_JAZZY)
    return _RecoveredReader(recovered, store)


@dataclass(frozen=True)
class TopicStats:
    """One connection of a bag: its messages' count, rate and gaps (bag times).

    Attributes:
        topic, msgtype: the connection. count: its messages.
        first_ns, last_ns: bag times of its first and last message.
        rate_hz: (count - 1) / (last - first), None with fewer than two messages or
            times. median_period_s: the median time between messages.
        gaps: (start ns, end ns) of every interval longer than ``gap_factor`` times the
            median period.
    """

    topic: str
    msgtype: str
    count: int
    first_ns: int
    last_ns: int
    rate_hz: float | None
    median_period_s: float | None
    gaps: tuple[tuple[int, int], ...]


def topic_stats(recovered: RecoveredBag, gap_factor: float = 3.0) -> list[TopicStats]:
    """Count, rate and gaps of each connection of a scanned bag, sorted by topic."""
    times: dict[int, list[int]] = {c.id: [] for c in recovered.connections}
    for cid, ns, _data in recovered.messages:
        times[cid].append(ns)
    out = []
    for c in recovered.connections:
        t = np.asarray(times[c.id], dtype=np.int64)
        if t.size == 0:
            out.append(TopicStats(c.topic, c.msgtype, 0, 0, 0, None, None, ()))
            continue
        dt = np.diff(t)
        span = int(t[-1] - t[0])
        rate = (t.size - 1) / (span * 1e-9) if span > 0 else None
        median = float(np.median(dt)) if dt.size else 0.0
        gaps: tuple[tuple[int, int], ...] = ()
        if median > 0:
            idx = np.flatnonzero(dt > gap_factor * median)
            gaps = tuple((int(t[i]), int(t[i + 1])) for i in idx)
        out.append(TopicStats(c.topic, c.msgtype, int(t.size), int(t[0]), int(t[-1]), rate,
                              median * 1e-9 if dt.size else None, gaps))
    return sorted(out, key=lambda st: (st.topic, st.msgtype))


def repair_bag(path: str | os.PathLike[str], out: str | os.PathLike[str],
               storage: str | None = None) -> RecoveredBag:
    """Write a clean, indexed copy of a (damaged) bag: every message a scan recovers.

    Args:
        path: the bag to read (see :func:`recover_bag`); never written to.
        out: the bag to write, atomically (a ``.bag`` file for ROS 1, else a directory).
        storage: "mcap", "sqlite3" or "ros1"; None keeps the input's format (mcap for a
            ROS 2 ``out`` of a ROS 1 input is refused: the serialisations differ).

    Returns:
        What was recovered (and written), with its damage report.

    Raises:
        BagError: nothing recoverable, a ROS 1 <-> ROS 2 conversion, or a write failure.
    """
    from rosbags.typesys import Stores, get_typestore

    recovered = recover_bag(path, record_order=True)
    parts = message_parts(recovered.messages)
    stepped = bool(parts.size and parts[-1])
    if stepped:  # the order written is kept: sorted by time the parts would interleave
        log.warning("%s: %s: the copy keeps the order its messages were written in (sorted "
                    "by time its parts would interleave)",
                    recovered.damage.bag, clock_steps_text([m[1] for m in recovered.messages],
                                                           parts))
    else:
        recovered.messages.sort(key=lambda m: m[1])  # stable: file order within one time
    out = Path(out)
    src = recovered.damage.storage
    if storage is None:
        storage = "ros1" if out.suffix == ".bag" else src
    if (storage == "ros1") != recovered.ros1:
        raise BagError(f"{out}: cannot write the {src} bag {recovered.damage.bag} as "
                       f"{storage}: repair keeps ROS 1 as ROS 1 and ROS 2 (mcap, sqlite3) "
                       "as ROS 2")
    if storage == "ros1" and out.suffix != ".bag":
        raise BagError(f"{out}: a ROS 1 bag must be a file ending in .bag")
    if storage != "ros1" and out.suffix == ".bag":
        raise BagError(f"{out}: a ROS 2 bag is a directory; give a name without .bag")
    store = _typestore_for(recovered, get_typestore(
        Stores.ROS1_NOETIC if recovered.ros1 else Stores.ROS2_JAZZY))
    offered = _offered_qos(path, recovered.ros1)
    content = BagContent(
        connections=[(c.topic, c.msgtype) for c in recovered.connections],
        messages=[(ns, cid, data) for cid, ns, data in recovered.messages],
        custom_data=recovered.custom_data, typestore=store,
        qos={c.id: offered[c.topic] for c in recovered.connections if c.topic in offered})
    write_bag(out, content, storage=storage, in_order=stepped)
    return recovered


def _offered_qos(path: str | os.PathLike[str], ros1: bool) -> dict[str, Any]:
    """By topic, how a bag's connections were offered, as its index tells (rosbags): a
    ROS 2 topic's offered QoS profiles, a ROS 1 topic's latching flag; empty when the index
    does not open (a damaged bag: its copy is offered with the defaults). A repaired copy
    lost them: a latched map replayed from it was volatile, and never reached the layer."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out: dict[str, Any] = {}
    try:
        with AnyReader([resolve_bag(path)], default_typestore=get_typestore(
                Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)) as reader:
            for c in reader.connections:
                ext = getattr(c, "ext", None)
                latching = getattr(ext, "latching", None)
                if ros1 and latching:
                    out.setdefault(c.topic, int(latching))
                profiles = getattr(ext, "offered_qos_profiles", None)
                if not ros1 and isinstance(profiles, list) and profiles:
                    out.setdefault(c.topic, profiles)
    except Exception:  # rosbags raises many types for a damaged index: the defaults
        return {}
    return out


# ----------------------------------------------------------------------------- writing
@dataclass(frozen=True)
class BagContent:
    """What :func:`write_bag` writes, whatever the data come from.

    Attributes:
        connections: (topic, message type) of each connection, in the order they are added;
            a type is named as rosbags names it (``"sensor_msgs/msg/Joy"``).
        messages: (bag time ns, connection index, serialised message), serialised for the
            bag's format (CDR for ROS 2, ROS 1 serialisation for a ``.bag``). Written in bag
            time order; messages with equal times keep their order here.
        custom_data: ``custom_data`` of a ROS 2 bag's metadata (not stored in a ROS 1 bag).
        typestore: a rosbags typestore that knows every message type (None: the standard
            store of the format).
        qos: by connection index, how it was offered: a ROS 2 connection's offered QoS
            profiles (rosbags ``Qos``), a ROS 1 connection's ``latching`` flag (a replay
            publishes a latched topic, a map, so that a late subscriber gets it).
    """

    connections: Sequence[tuple[str, str]]
    messages: Sequence[tuple[int, int, bytes]]
    custom_data: Mapping[str, str] = field(default_factory=dict)
    typestore: Any = None
    qos: Mapping[int, Any] = field(default_factory=dict)


class BagSource(Protocol):
    """Something that serialises itself as bag content for a format (e.g. a simulated
    recording)."""

    def bag_content(self, typestore: Any, ros1: bool) -> BagContent: ...


def serialise_batch(typestore: Any, ros1: bool, msgtype: str, make: Callable[..., Any],
                    fields: dict[str, str], values: dict[str, Any], n: int) -> list[bytes]:
    """``n`` serialised messages of one type whose variable fields are numpy columns.

    ``make(**row)`` builds one message from scalar field values; ``fields`` maps each
    variable field to its numpy type code (``"f8"``, ``"i4"``, ...) and ``values`` to its
    column (or a scalar). All messages share one layout (fixed strings and array lengths),
    so one message is serialised with a sentinel in every field and the columns are written
    into copies of it: byte-identical to serialising each message, and much faster.
    """
    serialize = typestore.serialize_ros1 if ros1 else typestore.serialize_cdr
    template, offsets = _layout(serialize, msgtype, make, fields)
    return _fill(template, offsets, values, n)


def _layout(serialize: Callable[[Any, str], Any], msgtype: str, make: Callable[..., Any],
            fields: dict[str, str]) -> tuple[bytes, dict[str, tuple[int, np.dtype]]]:
    """A serialised template message and the byte offset of each variable field."""
    sentinels: dict[str, float | int] = {}
    for k, (name, code) in enumerate(fields.items()):
        sentinels[name] = (1000.0 + 37.0 * k + 0.125) if code[0] == "f" else 0x3A5C0000 + 257 * k
    data = bytes(serialize(make(**sentinels), msgtype))
    offsets = {}
    for name, code in fields.items():
        dt = np.dtype("<" + code)
        pattern = np.array(sentinels[name], dtype=dt).tobytes()
        i = data.find(pattern)
        if i < 0 or data.find(pattern, i + 1) >= 0:  # pragma: no cover - layout guard
            raise RuntimeError(f"cannot locate field {name} in a serialised {msgtype}")
        offsets[name] = (i, dt)
    return data, offsets


def _fill(template: bytes, offsets: dict[str, tuple[int, np.dtype]],
          values: dict[str, Any], n: int) -> list[bytes]:
    """``n`` serialised messages: the template with each field's column written in."""
    buf = np.tile(np.frombuffer(template, dtype=np.uint8), (n, 1))  # [n, L]
    for name, (off, dt) in offsets.items():
        col = np.ascontiguousarray(np.broadcast_to(values[name], (n,)), dtype=dt)
        buf[:, off:off + dt.itemsize] = col.view(np.uint8).reshape(n, dt.itemsize)
    return [row.tobytes() for row in buf]


def write_bag(
    path: str | os.PathLike[str],
    content: BagContent | BagSource,
    storage: str = "mcap",
    *,
    in_order: bool = False,
) -> Path:
    """Write messages as a bag, atomically and reproducibly.

    Args:
        path: the bag to create: a ROS 2 bag directory, or a ``.bag`` file for ROS 1.
            An existing bag at ``path`` is replaced only once the new one is complete.
        content: the messages (:class:`BagContent`, serialised for this format), or a
            :class:`BagSource` that serialises itself for the format (a simulated
            recording: :meth:`asgp_ros.sim.simulate.Recording.bag_content`).
        storage: "mcap" (default) or "sqlite3" for ROS 2, "ros1" for a ROS 1 bag (chosen
            automatically for a ``.bag`` path).
        in_order: write the messages in the order given, not sorted by bag time (a
            recording whose clock stepped back: the order it was written in alone tells its
            parts apart, :func:`clock_parts`).

    Returns:
        The path written.
    """
    from rosbags.rosbag1 import WriterError as WriterError1
    from rosbags.rosbag2 import WriterError as WriterError2
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    if path.suffix == ".bag":
        storage = "ros1"
    if storage not in STORAGES:
        raise BagError(f"{path}: unknown storage {storage!r}; expected one of {STORAGES}")
    ros1 = storage == "ros1"
    if ros1 and path.suffix != ".bag":
        raise BagError(f"{path}: a ROS 1 bag must be a file ending in .bag")
    default_store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_JAZZY)
    if not isinstance(content, BagContent):
        content = content.bag_content(default_store, ros1)
    store = content.typestore if content.typestore is not None else default_store
    records = content.messages
    # the times the format holds: ROS 1 uint32 seconds, ROS 2 from 0 to int64 (mcap's are
    # unsigned, sqlite3's signed); a negative time (an SQLite bag may hold one) made the mcap
    # writer raise OverflowError
    limit = (1 << 32) * 1_000_000_000 if ros1 else 1 << 63
    bad = next((r[0] for r in records
                if not (isinstance(r[0], int | np.integer) and 0 <= r[0] < limit)), None)
    if bad is not None:
        raise BagError(f"{path}: cannot write a message with the bag time "
                       f"{_one_line(repr(bad))[:30]} ns in a {storage} bag: its times run "
                       f"from 0 to {limit * 1e-9:.4g} s")
    order = (range(len(records)) if in_order
             else sorted(range(len(records)), key=lambda i: (records[i][0], i)))
    try:
        with atomic_path(path, directory=not ros1) as tmp:
            if ros1:
                from rosbags.rosbag1 import Writer as Writer1

                with Writer1(tmp) as w1:
                    conns1 = [w1.add_connection(t, m, typestore=store,
                                                latching=content.qos.get(i))
                              for i, (t, m) in enumerate(content.connections)]
                    for i in order:
                        ts, c, data = records[i]
                        w1.write(conns1[c], ts, data)
            else:
                from rosbags.rosbag2 import StoragePlugin, Writer

                plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
                with Writer(tmp, version=9, storage_plugin=plugin) as w2:
                    for key, value in content.custom_data.items():
                        w2.set_custom_data(key, value)
                    conns2 = [w2.add_connection(t, m, typestore=store,
                                                offered_qos_profiles=content.qos.get(i, ()))
                              for i, (t, m) in enumerate(content.connections)]
                    for i in order:
                        ts, c, data = records[i]
                        w2.write(conns2[c], ts, data)
    except (OSError, WriterError1, WriterError2, sqlite3.Error) as exc:
        # (sqlite3's: rosbags' sqlite3 storage on a full disk, "database or disk is full")
        raise BagError(f"{path}: cannot write bag: {_one_line(exc)}") from exc
    return path
