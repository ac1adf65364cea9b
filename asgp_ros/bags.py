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

Failures raise ``BagError`` naming the file and the problem, in one line: no such bag,
not a bag, a corrupt or truncated file, a missing topic (with the list of topics the bag
has), an unsupported message type.

Paths are checked with ``os.stat`` before anything is opened (:func:`resolve_bag`): a bag
is a regular ROS 1 ``.bag`` file or a ROS 2 bag directory whose ``metadata.yaml`` (at
most ``MAX_BAG_METADATA_BYTES``) and storage files are regular files; a FIFO, a device,
a socket, a dangling link or a directory where a file goes is refused, naming the path,
so a reader never blocks on it.
"""

from __future__ import annotations

import logging
import os
import re
import stat
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from asgp_ros.core.modelfile import file_type_problem, loads_bounded, regular_file_problem
from asgp_ros.core.quaternion import quaternion_to_yaw
from asgp_ros.core.streams import RawStreams, joy_in_range, vel_in_range
from asgp_ros.fileio import ROS1_MAGIC, atomic_path
from asgp_ros.topics import BAG_JOY, BAG_VO_TWIST

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

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


def parse_joy_axes(spec: str) -> JoyAxes:
    """Parse the ``--joy-axes`` syntax ``FWD,TURN``.

    Each of FWD and TURN is an index into ``Joy.axes``, optionally prefixed with ``-`` to
    flip its sign. ``"0,1"`` (the default, as published by this package's bridge) means
    forward = axes[0], turn = axes[1]; ``"1,-0"`` means forward = axes[1],
    turn = -axes[0]; a typical gamepad's left stick is ``"1,0"``.
    """
    parts = spec.split(",")
    if len(parts) != 2:
        raise ValueError(f"--joy-axes {spec!r}: expected FWD,TURN such as '0,1' or '1,-0'")
    parsed = []
    for part in parts:
        m = _AXIS_RE.match(part)
        if m is None:
            raise ValueError(
                f"--joy-axes {spec!r}: {part!r} is not an axis index with an optional '-'"
            )
        parsed.append((int(m.group(2)), -1.0 if m.group(1) == "-" else 1.0))
    (f, fs), (t, ts) = parsed
    try:
        return JoyAxes(forward=f, turn=t, forward_sign=fs, turn_sign=ts)
    except ValueError as exc:
        raise ValueError(f"--joy-axes {spec!r}: {exc}") from None


# ----------------------------------------------------------------------------- reading
def _one_line(text: object) -> str:
    """An error text on one line (library messages may span several)."""
    return " ".join(str(text).split())


def _bag_metadata(bag: Path) -> dict[str, Any]:
    """The parsed ``metadata.yaml`` of a ROS 2 bag directory (size checked first)."""
    import yaml

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


def resolve_bag(path: str | os.PathLike[str]) -> Path:
    """The bag ``path`` names, checked with ``os.stat`` before anything is opened.

    A ROS 1 ``.bag`` file, a ROS 2 bag directory, or a storage file inside one (which
    stands for its directory).

    Raises:
        BagError: no such path, not a bag, or a FIFO / device / socket / dangling link
            where a bag or one of its files should be (naming that path).
    """
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        raise BagError(f"{p}: no such bag") from None
    except (OSError, ValueError) as exc:
        raise BagError(f"{p}: cannot be read: "
                       f"{_one_line(getattr(exc, 'strerror', None) or exc)}") from None
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


def _choose_times(name: str, stamp_ns: NDArray[np.int64] | None, bag_ns: NDArray[np.int64],
                  max_skew: float, source: str) -> FloatArray:
    """Header stamps where valid, bag time (minus the median latency) elsewhere; seconds."""
    bag = bag_ns.astype(np.float64) * 1e-9
    if stamp_ns is None:
        return bag
    stamp = stamp_ns.astype(np.float64) * 1e-9
    valid = (stamp_ns > 0) & (np.abs(stamp - bag) <= max_skew)
    if not valid.any():
        log.warning("%s: %s has no valid header stamps; using bag time", source, name)
        return bag
    if not valid.all():
        log.warning("%s: %s: %d of %d header stamps invalid (zero or > %.1f s from bag "
                    "time); using bag time for those", source, name, int((~valid).sum()),
                    valid.size, max_skew)
    latency = float(np.median(bag[valid] - stamp[valid]))
    return np.where(valid, stamp, bag - latency)


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
             source: str) -> tuple[list[int], list[tuple[Any, ...]]]:
    bag_ns: list[int] = []
    rows: list[tuple[Any, ...]] = []
    try:
        for conn, timestamp, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            bag_ns.append(int(timestamp))
            rows.append(extract(msg, conn.msgtype))
    except BagError:
        raise
    except Exception as exc:  # rosbags raises several types for damaged data
        raise BagError(f"{source}: corrupt or truncated bag: "
                       f"{_one_line(f'{type(exc).__name__}: {exc}')}") from exc
    return bag_ns, rows


def read_streams(
    path: str | os.PathLike[str],
    joy_topic: str = BAG_JOY,
    twist_topic: str = BAG_VO_TWIST,
    truth_topic: str | None = None,
    joy_axes: JoyAxes | str | None = None,
    max_stamp_skew: float = 10.0,
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

    Returns:
        RawStreams with times in seconds on the bag's clock (header stamps where valid).

    Raises:
        BagError: missing file or topic, unsupported type, corrupt or truncated bag.
    """
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    if joy_axes is None:
        joy_axes = JoyAxes()
    axes = parse_joy_axes(joy_axes) if isinstance(joy_axes, str) else joy_axes
    bag = resolve_bag(path)
    source = str(bag)
    is_ros1 = bag.is_file()
    store = get_typestore(Stores.ROS1_NOETIC if is_ros1 else Stores.ROS2_JAZZY)
    try:
        reader = AnyReader([bag], default_typestore=store)
        reader.open()
    except BagError:
        raise
    except Exception as exc:
        hint = ("; a bag whose recording was killed may need `rosbag reindex` (ROS 1) "
                "or `ros2 bag reindex` (ROS 2)")
        raise BagError(f"{source}: cannot open bag (corrupt or truncated): "
                       f"{_one_line(f'{type(exc).__name__}: {exc}')}{hint}") from exc
    try:
        joy_conns = _connections(reader, joy_topic, JOY_TYPES, "joystick", source)
        tw_conns = _connections(reader, twist_topic, TWIST_TYPES, "velocity", source)
        tr_conns = (_connections(reader, truth_topic, TRUTH_TYPES, "ground truth", source)
                    if truth_topic else [])
        need = max(axes.forward, axes.turn) + 1

        def joy_row(msg: Any, _t: str) -> tuple[Any, ...]:
            a = msg.axes
            if len(a) < need:
                raise BagError(
                    f"{source}: {joy_topic} has {len(a)} axes, --joy-axes {axes} needs {need}"
                )
            return (_stamp_ns(msg), axes.forward_sign * float(a[axes.forward]),
                    axes.turn_sign * float(a[axes.turn]))

        def twist_row(msg: Any, msgtype: str) -> tuple[Any, ...]:
            if msgtype == "geometry_msgs/msg/Twist":
                return (0, msg.linear.x, msg.angular.z)
            tw = msg.twist if msgtype == "geometry_msgs/msg/TwistStamped" else msg.twist.twist
            return (_stamp_ns(msg), tw.linear.x, tw.angular.z)

        def truth_row(msg: Any, _t: str) -> tuple[Any, ...]:
            p = msg.pose.pose
            tw = msg.twist.twist
            q = p.orientation
            return (_stamp_ns(msg), p.position.x, p.position.y,
                    float(quaternion_to_yaw(q.x, q.y, q.z, q.w)), tw.linear.x, tw.angular.z)

        jb, jr = _collect(reader, joy_conns, joy_row, source)
        vb, vr = _collect(reader, tw_conns, twist_row, source)
        tb, tr = _collect(reader, tr_conns, truth_row, source) if tr_conns else ([], [])
    finally:
        reader.close()

    for name, topic, rows in (("joystick", joy_topic, jr), ("velocity", twist_topic, vr)):
        if not rows:
            raise BagError(f"{source}: {name} topic {topic!r} has no messages")
    j = np.asarray(jr, dtype=np.float64).reshape(-1, 3)
    v = np.asarray(vr, dtype=np.float64).reshape(-1, 3)
    has_header = tw_conns[0].msgtype != "geometry_msgs/msg/Twist"
    joy_t = _choose_times(joy_topic, np.asarray([r[0] for r in jr], dtype=np.int64),
                          np.asarray(jb, dtype=np.int64), max_stamp_skew, source)
    vel_t = _choose_times(
        twist_topic, np.asarray([r[0] for r in vr], dtype=np.int64) if has_header else None,
        np.asarray(vb, dtype=np.int64), max_stamp_skew, source)
    truth_t = np.zeros(0)
    truth = np.zeros((0, 5))
    if tr:
        ta = np.asarray(tr, dtype=np.float64).reshape(-1, 6)
        truth_t = _choose_times(truth_topic or "", np.asarray([r[0] for r in tr], np.int64),
                                np.asarray(tb, dtype=np.int64), max_stamp_skew, source)
        truth = ta[:, 1:]
    for name, topic, bad, n in (
            ("joystick", joy_topic, int(np.count_nonzero(~joy_in_range(j[:, 1:]))), j.shape[0]),
            ("velocity", twist_topic, int(np.count_nonzero(~vel_in_range(v[:, 1:]))),
             v.shape[0])):
        if bad:  # the resampler drops them; a large share means a wrong scale or topic
            log.warning("%s: %d of %d %s samples on %s are not finite or outside their "
                        "physical range (asgp_ros.core.streams); they are dropped", source,
                        bad, n, name, topic)
    try:
        return RawStreams(joy_t=joy_t, joy=j[:, 1:], vel_t=vel_t, vel=v[:, 1:],
                          truth_t=truth_t, truth=truth, source=source)
    except ValueError as exc:
        raise BagError(f"{source}: {exc}") from exc


def bag_topics(path: str | os.PathLike[str]) -> dict[str, str]:
    """Topic name -> message type of a bag."""
    from rosbags.highlevel import AnyReader

    bag = resolve_bag(path)
    try:
        with AnyReader([bag]) as reader:
            return {c.topic: c.msgtype for c in reader.connections}
    except Exception as exc:
        raise BagError(f"{bag}: cannot open bag: "
                       f"{_one_line(f'{type(exc).__name__}: {exc}')}") from exc


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
    """

    connections: Sequence[tuple[str, str]]
    messages: Sequence[tuple[int, int, bytes]]
    custom_data: Mapping[str, str] = field(default_factory=dict)
    typestore: Any = None


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
    order = sorted(range(len(records)), key=lambda i: (records[i][0], i))
    try:
        with atomic_path(path, directory=not ros1) as tmp:
            if ros1:
                from rosbags.rosbag1 import Writer as Writer1

                with Writer1(tmp) as w1:
                    conns1 = [w1.add_connection(t, m, typestore=store)
                              for t, m in content.connections]
                    for i in order:
                        ts, c, data = records[i]
                        w1.write(conns1[c], ts, data)
            else:
                from rosbags.rosbag2 import StoragePlugin, Writer

                plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
                with Writer(tmp, version=9, storage_plugin=plugin) as w2:
                    for key, value in content.custom_data.items():
                        w2.set_custom_data(key, value)
                    conns2 = [w2.add_connection(t, m, typestore=store)
                              for t, m in content.connections]
                    for i in order:
                        ts, c, data = records[i]
                        w2.write(conns2[c], ts, data)
    except (OSError, WriterError1, WriterError2) as exc:
        raise BagError(f"{path}: cannot write bag: {_one_line(exc)}") from exc
    return path
