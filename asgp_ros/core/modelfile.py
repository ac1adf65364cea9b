"""The model file: one ``.npz`` holding a trained two-channel predictor.

Layout (format version 1):

* ``__meta__``: a 0-d unicode array holding one JSON object::

      {"format": "asgp_ros.motion_model", "format_version": 1, "kind": "asgp",
       "channels": ["v", "omega"], "features": {"lags": 4, "coupled": false},
       "resample": {"rate_hz": 5.0, ...}, "rate_hz": 5.0,
       "kind_params": {...}, "normalisation": ..., "meta": {training data summary, ...},
       "calibration": {"scale": [a_v, a_w], "floor": [b_v, b_w]},
       "arrays": {"v.alpha": [20], ...}}

  ``calibration`` (:mod:`asgp_ros.core.calibration`) is optional: a file without it has
  the identity map.

* one numeric array per entry of ``arrays`` (names ``<channel>.<field>`` by convention),
  as the kind's ``to_arrays`` produced them (:mod:`asgp_ros.core.models`).

The file is written atomically (:func:`asgp_ros.common.fileio.atomic_path`: a failed save leaves
any previous file untouched). Nothing in it is executable, and nothing in it is trusted:
:func:`load_model` reads it in this order and refuses (:class:`ModelFileError`, naming the
file and the problem) at the first thing that does not validate:

1. the path: ``os.stat`` before opening; only a regular file of at most ``MAX_FILE_BYTES``
   (a FIFO, a device, a socket or a directory is refused without being opened, so a
   reader never blocks on it);
2. the archive's directory: at most ``MAX_MEMBERS`` ``.npy`` members, stored or deflated;
3. every member's ``.npy`` header (``numpy.lib.format``): a plain numeric dtype (unicode
   for the metadata), at most ``MAX_NDIM`` dimensions and ``MAX_ARRAY_ELEMENTS`` elements,
   and exactly as many data bytes as the header declares (``MAX_DATA_BYTES`` in all) --
   before any array data is read, so a header declaring 10**10 elements allocates nothing;
4. the metadata: at most ``MAX_META_CHARS`` characters nested at most ``MAX_META_DEPTH``
   deep, finite numbers only (:func:`loads_bounded`); every number the model uses is
   checked against its documented range (``rate_hz`` and the resampling settings:
   :data:`asgp_ros.core.resample.RESAMPLE_RANGES`; ``lags``:
   :data:`asgp_ros.core.features.LAGS_RANGE`; array shapes as in 3.);
5. the manifest against the headers, then the data: finite, ``|x| <= MAX_ABS_VALUE``,
   normalisation entries within ``NORMALISATION_RANGES``, the calibration within
   :data:`~asgp_ros.core.calibration.SCALE_RANGE` and ``FLOOR_RANGE``; then the kind's own
   checks.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import stat
import struct
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np

from asgp_ros.common.fileio import atomic_path
from asgp_ros.core.calibration import CalibrationError, VarianceCalibration
from asgp_ros.core.features import CHANNELS, FeatureConfig
from asgp_ros.core.models import MotionModel, get_kind, registered_kinds
from asgp_ros.core.resample import RESAMPLE_RANGES, ResampleConfig

logger = logging.getLogger(__name__)

FORMAT_NAME = "asgp_ros.motion_model"
FORMAT_VERSION = 1
META_KEY = "__meta__"
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.]{0,127}")
_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)

# Limits of a model file (a trained model is a few hundred kB; these are generous). Each
# is checked before the thing it bounds is read or allocated.
#: Size of the whole file (bytes).
MAX_FILE_BYTES = 64 * 2**20
#: Members of the archive (a model has a few dozen arrays).
MAX_MEMBERS = 256
#: Dimensions of one array.
MAX_NDIM = 4
#: Elements of one array (a 2048 x 2048 covariance).
MAX_ARRAY_ELEMENTS = 2**22
#: Data bytes of all arrays together, uncompressed.
MAX_DATA_BYTES = 64 * 2**20
#: Characters of the JSON metadata.
MAX_META_CHARS = 2**20
#: Nesting depth of the JSON metadata (the writer nests 3 levels).
MAX_META_DEPTH = 32
#: Largest |value| of any array element (squares stay far from float64 overflow).
MAX_ABS_VALUE = 1e15
_MEAN_RANGE = (-1e6, 1e6)
_SCALE_RANGE = (1e-12, 1e6)
#: Normalisation arrays (the name after ``<channel>.``): the range of every element, or a
#: tuple with one range per element (the MLP's ``y_norm`` = (mean, scale)).
NORMALISATION_RANGES: dict[str, Any] = {
    "x_mean": _MEAN_RANGE,
    "x_scale": _SCALE_RANGE,
    "y_mean": _MEAN_RANGE,
    "y_scale": _SCALE_RANGE,
    "y_norm": (_MEAN_RANGE, _SCALE_RANGE),
}
_NPY_MAGIC = b"\x93NUMPY"
_EOCD = struct.Struct("<4s4H2LH")  # end of central directory record


class ModelFileError(ValueError):
    """A model file that cannot be written or does not validate.

    Attributes:
        path: the file.
        problem: what is wrong with it.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = str(path)
        self.problem = problem
        super().__init__(f"model file {self.path}: {problem}")


# ----------------------------------------------------------------------- reading safely

_FILE_TYPES = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
               (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
               (stat.S_ISSOCK, "a socket"))


def file_type_problem(mode: int) -> str | None:
    """Why a path whose ``st_mode`` is ``mode`` is not a regular file, or None if it is."""
    if stat.S_ISREG(mode):
        return None
    for is_type, what in _FILE_TYPES:
        if is_type(mode):
            return f"is {what}, not a regular file"
    return "is not a regular file"


def regular_file_problem(path: str | os.PathLike[str],
                         max_bytes: int | None = None) -> str | None:
    """Why ``path`` cannot be read as a regular file (``os.stat``, nothing is opened).

    Returns None for a regular file of at most ``max_bytes``; otherwise "no such file",
    "is a FIFO (named pipe), not a regular file", ..., in words to follow the path.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "no such file"
    except (OSError, ValueError) as exc:
        return f"cannot be read: {getattr(exc, 'strerror', None) or exc}"
    problem = file_type_problem(st.st_mode)
    if problem is None and max_bytes is not None and st.st_size > max_bytes:
        problem = f"is {st.st_size} bytes, more than the limit of {max_bytes}"
    return problem


@contextmanager
def open_regular_file(path: str | os.PathLike[str],
                      max_bytes: int | None = None) -> Iterator[IO[bytes]]:
    """Open a regular file for binary reading without ever blocking on anything else.

    The path is checked with :func:`regular_file_problem` before it is opened, and opened
    non-blocking and checked again with ``fstat``, so a path replaced by a FIFO or a
    device between the two is refused too.

    Raises:
        ValueError: the problem in words (the caller names the path).
    """
    problem = regular_file_problem(path, max_bytes)
    if problem is not None:
        raise ValueError(problem)
    flags = (os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
             | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise ValueError(f"cannot be opened: {exc.strerror or exc}") from exc
    try:
        st = os.fstat(fd)
        problem = file_type_problem(st.st_mode)
        if problem is None and max_bytes is not None and st.st_size > max_bytes:
            problem = f"is {st.st_size} bytes, more than the limit of {max_bytes}"
        if problem is not None:
            raise ValueError(problem)
        os.set_blocking(fd, True)
        fh = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    with fh:
        yield fh


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text} is beyond the range of a float")
    return value


def _bounded_int(text: str) -> int:
    value = int(text)
    if not -(1 << 63) <= value < 1 << 63:
        raise ValueError(f"integer {text[:20]}{'...' if len(text) > 20 else ''} is beyond "
                         "64 bits")
    return value


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a finite number")


def loads_bounded(text: str, max_chars: int = MAX_META_CHARS,
                  max_depth: int = MAX_META_DEPTH) -> Any:
    """``json.loads`` for untrusted text: size and nesting bounded, numbers finite.

    The nesting is measured on the text before parsing (brackets outside strings), so a
    deeply nested document is refused without recursing into it.

    Raises:
        ValueError: too long, nested too deeply, NaN / Infinity / an overflowing number
            (an integer beyond 64 bits too), or not JSON.
    """
    if len(text) > max_chars:
        raise ValueError(f"{len(text)} characters, more than the limit of {max_chars}")
    code = np.frombuffer(_JSON_STRING.sub('""', text).encode("utf-8", "surrogatepass"),
                         dtype=np.uint8)
    step = (np.isin(code, _JSON_OPEN).astype(np.int64)
            - np.isin(code, _JSON_CLOSE).astype(np.int64))
    depth = int(np.cumsum(step).max()) if step.size else 0
    if depth > max_depth:
        raise ValueError(f"nested {depth} levels deep, more than the limit of {max_depth}")
    try:
        return json.loads(text, parse_float=_finite_float, parse_int=_bounded_int,
                          parse_constant=_no_constant)
    except RecursionError:  # pragma: no cover - the depth check comes first
        raise ValueError(f"nested more than {max_depth} levels deep") from None


_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.DOTALL)
_JSON_OPEN = np.frombuffer(b"[{", dtype=np.uint8)
_JSON_CLOSE = np.frombuffer(b"]}", dtype=np.uint8)


def _shape_problem(shape: object) -> str | None:
    """Why ``shape`` (a manifest entry or a header's shape) is not allowed, or None."""
    if not isinstance(shape, list | tuple):
        return f"shape {shape!r} is not a list"
    if len(shape) > MAX_NDIM:
        return f"shape {list(shape)} has more than {MAX_NDIM} dimensions"
    for n in shape:
        if isinstance(n, bool) or not isinstance(n, int) or not 0 <= n <= MAX_ARRAY_ELEMENTS:
            return f"shape {list(shape)} has a size outside [0, {MAX_ARRAY_ELEMENTS}]"
    if math.prod(shape) > MAX_ARRAY_ELEMENTS:
        return f"shape {list(shape)} has more than {MAX_ARRAY_ELEMENTS} elements"
    return None


def _value_problem(name: str, arr: np.ndarray) -> str | None:
    """Why the values of array ``name`` are not allowed (non-finite, huge, normalisation
    outside ``NORMALISATION_RANGES``), or None."""
    if arr.dtype.kind not in "fiub":
        return f"has non-numeric dtype {arr.dtype}"
    if arr.dtype.kind == "b" or arr.size == 0:
        return None
    if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
        return "contains NaN or inf"
    if float(np.max(np.abs(arr.astype(np.float64)))) > MAX_ABS_VALUE:
        return f"has a value beyond +-{MAX_ABS_VALUE:g}"
    ranges = NORMALISATION_RANGES.get(name.rsplit(".", 1)[-1])
    if ranges is None:
        return None
    flat = arr.astype(np.float64).reshape(-1)
    per_element = isinstance(ranges[0], tuple)
    if per_element and flat.shape[0] != len(ranges):
        return f"must have {len(ranges)} entries, has {flat.shape[0]}"
    for i, x in enumerate(flat):
        low, high = ranges[i] if per_element else ranges
        if not low <= x <= high:
            return f"normalisation entry {i} = {x:g} is outside [{low:g}, {high:g}]"
    return None


def _check_arrays(path: str | os.PathLike[str],
                  arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if len(arrays) >= MAX_MEMBERS:
        raise ModelFileError(path, f"{len(arrays)} arrays, more than {MAX_MEMBERS - 1}")
    out: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
            raise ModelFileError(path, f"array name {name!r} is not allowed")
        arr = np.asarray(value)
        problem = _shape_problem(list(arr.shape)) or _value_problem(name, arr)
        if problem is not None:
            raise ModelFileError(path, f"array {name!r} {problem}")
        out[name] = arr
    return out


def save_model(path: str | os.PathLike[str], model: MotionModel) -> None:
    """Write ``model`` to ``path`` (one .npz, atomically; see the module docstring).

    Raises:
        ModelFileError: the model cannot be stored (unknown kind, arrays or metadata that
            :func:`load_model` would refuse: non-finite or out-of-range values, too large,
            metadata that is not JSON or nested too deeply, predictions beyond a
            wheelchair's limits).
    """
    try:
        kind = get_kind(model.kind)
    except KeyError as exc:
        raise ModelFileError(path, str(exc.args[0])) from None
    arrays, params = kind.to_arrays(model)
    arrays = _check_arrays(path, arrays)
    meta: dict[str, Any] = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "kind": model.kind,
        "channels": list(CHANNELS),
        "features": model.feature_config.to_dict(),
        "resample": model.resample_config.to_dict(),
        "rate_hz": model.resample_config.rate_hz,
        "kind_params": params,
        "normalisation": params.get("normalisation", "stored in the kind's arrays"),
        "meta": model.meta,
        "calibration": model.calibration.to_dict(),
        "arrays": {name: list(arr.shape) for name, arr in arrays.items()},
    }
    try:
        text = json.dumps(meta, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ModelFileError(path, f"metadata is not plain JSON: {exc}") from exc
    try:
        loads_bounded(text)  # never write a file that load_model would refuse
    except ValueError as exc:
        raise ModelFileError(path, f"metadata cannot be stored: {exc}") from exc
    problem = probe_problem(model)  # as load_model checks it: never a file it refuses
    if problem is not None:
        raise ModelFileError(path, f"not a wheelchair's model: {problem}")
    payload: dict[str, Any] = {META_KEY: np.array(text), **arrays}
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            # a file object, so numpy does not append ".npz" to the temporary name
            np.savez(fh, **payload)
    except OSError as exc:
        if exc.filename is not None:
            raise
        # (a full disk said only "No space left on device": the user needs the file)
        raise OSError(exc.errno, exc.strerror or str(exc), os.fspath(path)) from exc
    logger.info("saved %s model to %s", model.kind, path)


class _Member:
    """One ``.npy`` member of the archive, its header checked (nothing of its data read)."""

    def __init__(self, info: zipfile.ZipInfo, shape: tuple[int, ...], fortran: bool,
                 dtype: np.dtype[Any], offset: int) -> None:
        self.info = info
        self.shape = shape
        self.fortran = fortran
        self.dtype = dtype
        self.offset = offset  # bytes of magic and header before the data
        self.nbytes = math.prod(shape) * dtype.itemsize


def _zip_directory_problem(fh: IO[bytes], size: int) -> str | None:
    """Check the archive's end record (entry count, directory size) before zipfile parses
    the directory, so a forged count cannot make it build millions of entries."""
    tail = min(size, _EOCD.size + 0xFFFF)
    fh.seek(size - tail)
    data = fh.read(tail)
    at = data.rfind(b"PK\x05\x06")
    if at < 0 or len(data) - at < _EOCD.size:
        return None  # not a zip: zipfile says so below
    _sig, _disk, _cd_disk, _here, entries, cd_size, _cd_off, _comment = _EOCD.unpack_from(data, at)
    if entries > MAX_MEMBERS:
        return f"the archive has {entries} members, more than {MAX_MEMBERS}"
    if cd_size > MAX_MEMBERS * (46 + 3 * 0xFFFF):
        return f"the archive's directory is {cd_size} bytes"
    return None


def _read_header(path: Path, zf: zipfile.ZipFile, info: zipfile.ZipInfo, key: str) -> _Member:
    """The checked ``.npy`` header of one member (reads only the header)."""
    what = "metadata" if key == META_KEY else f"array {key!r}"
    if info.flag_bits & 0x1:
        raise ModelFileError(path, f"{what} cannot be read: it is encrypted")
    if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
        raise ModelFileError(path, f"{what} cannot be read: unsupported compression "
                                   f"{info.compress_type}")
    if info.file_size > MAX_DATA_BYTES + 4096:
        raise ModelFileError(path, f"{what} is {info.file_size} bytes, more than the limit "
                                   f"of {MAX_DATA_BYTES}")
    try:
        with zf.open(info) as f:
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                header = np.lib.format.read_array_header_1_0(f, max_header_size=4096)
            elif version == (2, 0):
                header = np.lib.format.read_array_header_2_0(f, max_header_size=4096)
            else:
                raise ValueError(f"unsupported .npy format version {version}")
            offset = f.tell()
    except Exception as exc:  # numpy parses the header text: SyntaxError, TokenError, ...
        raise ModelFileError(path, f"{what} cannot be read (truncated or corrupt header: "
                                   f"{type(exc).__name__}: {exc})") from exc
    shape, fortran, dtype = header
    if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
        raise ModelFileError(path, f"{what} cannot be read: dtype {dtype} is not a plain "
                                   "numeric type (objects are never unpickled)")
    if key == META_KEY:
        if dtype.kind != "U" or shape != ():
            raise ModelFileError(path, f"metadata {META_KEY!r} is not a JSON string")
        if dtype.itemsize > 4 * MAX_META_CHARS:
            raise ModelFileError(path, f"metadata is {dtype.itemsize // 4} characters, more "
                                       f"than the limit of {MAX_META_CHARS}")
    else:
        if dtype.kind not in "fiub" or dtype.itemsize > 16:
            raise ModelFileError(path, f"array {key!r} cannot be read: non-numeric dtype "
                                       f"{dtype}")
        problem = _shape_problem(shape)
        if problem is not None:
            raise ModelFileError(path, f"array {key!r} cannot be read: its header's {problem}")
    member = _Member(info, tuple(shape), bool(fortran), dtype, offset)
    if info.file_size - offset != member.nbytes:
        raise ModelFileError(
            path, f"{what} cannot be read: its header declares {member.nbytes} data bytes, "
                  f"the archive holds {info.file_size - offset}")
    return member


def _read_data(path: Path, zf: zipfile.ZipFile, member: _Member, key: str) -> np.ndarray:
    """The data of a member whose header :func:`_read_header` checked."""
    what = "metadata" if key == META_KEY else f"array {key!r}"
    try:
        with zf.open(member.info) as f:
            f.read(member.offset)
            data = f.read(member.nbytes)
            if len(data) != member.nbytes or f.read(1):
                raise EOFError(f"{len(data)} of {member.nbytes} data bytes")
    except _READ_ERRORS as exc:
        raise ModelFileError(
            path, f"{what} cannot be read (truncated or corrupt: {exc})") from exc
    flat = np.frombuffer(data, dtype=member.dtype)
    arr = flat.reshape(member.shape[::-1]).T if member.fortran else flat.reshape(member.shape)
    return np.array(arr, dtype=member.dtype.newbyteorder("="))


@contextmanager
def _open_npz(path: Path) -> Iterator[tuple[zipfile.ZipFile, dict[str, _Member]]]:
    """The archive and the checked headers of its members (steps 1-3 of the module doc)."""
    with ExitStack() as stack:
        try:
            fh = stack.enter_context(open_regular_file(path, MAX_FILE_BYTES))
        except ValueError as exc:
            raise ModelFileError(path, str(exc)) from None
        size = os.fstat(fh.fileno()).st_size
        if fh.read(len(_NPY_MAGIC)) == _NPY_MAGIC:
            raise ModelFileError(path, "not an .npz model file (a single .npy array)")
        problem = _zip_directory_problem(fh, size)
        if problem is not None:
            raise ModelFileError(path, f"not a model file: {problem}")
        fh.seek(0)
        try:
            zf = stack.enter_context(zipfile.ZipFile(fh))
        except _READ_ERRORS as exc:
            raise ModelFileError(
                path, f"not an .npz model file (unreadable or truncated archive: {exc})"
            ) from exc
        members: dict[str, _Member] = {}
        total = 0
        for info in zf.infolist():
            name = info.filename
            key = name[:-4] if name.endswith(".npy") else name
            if not name.endswith(".npy") or not (key == META_KEY or _NAME_RE.fullmatch(key)):
                raise ModelFileError(path, f"unexpected archive member {name!r}")
            if key in members:
                raise ModelFileError(path, f"archive member {name!r} appears twice")
            members[key] = _read_header(path, zf, info, key)
            total += members[key].nbytes
            if total > MAX_DATA_BYTES:
                raise ModelFileError(path, f"the arrays hold more than {MAX_DATA_BYTES} bytes")
        if META_KEY not in members:
            raise ModelFileError(path, f"no metadata entry {META_KEY!r} (not a model file)")
        yield zf, members


def _require(path: Path, meta: dict[str, Any], key: str, typ: type | tuple[type, ...]) -> Any:
    if key not in meta:
        raise ModelFileError(path, f"metadata lacks {key!r}")
    value = meta[key]
    if not isinstance(value, typ) or (isinstance(value, bool) and typ is not bool):
        raise ModelFileError(path, f"metadata {key!r} has the wrong type ({value!r})")
    return value


def _check_meta(p: Path, meta: Any, kind: str | None
                ) -> tuple[str, FeatureConfig, ResampleConfig, dict[str, Any]]:
    """Kind, settings and array manifest of parsed metadata (every number range-checked)."""
    if not isinstance(meta, dict):
        raise ModelFileError(p, "metadata is not a JSON object")
    fmt = meta.get("format")
    if fmt != FORMAT_NAME:
        raise ModelFileError(p, f"not an asgp_ros model file (format {fmt!r})")
    version = _require(p, meta, "format_version", int)
    if version != FORMAT_VERSION:
        newer = " (written by a newer asgp_ros)" if version > FORMAT_VERSION else ""
        raise ModelFileError(
            p, f"format version {version}{newer}; this version reads {FORMAT_VERSION}"
        )
    kind_name = _require(p, meta, "kind", str)
    if kind is not None and kind_name != kind:
        raise ModelFileError(p, f"holds a {kind_name!r} model, expected {kind!r}")
    channels = _require(p, meta, "channels", list)
    if channels != list(CHANNELS):
        raise ModelFileError(p, f"channels {channels!r}, expected {list(CHANNELS)!r}")
    try:
        features = FeatureConfig.from_dict(_require(p, meta, "features", dict))
        resample_cfg = ResampleConfig.from_dict(_require(p, meta, "resample", dict))
    except (TypeError, ValueError) as exc:
        if isinstance(exc, ModelFileError):
            raise
        raise ModelFileError(p, f"invalid settings: {exc}") from exc
    rate = meta.get("rate_hz", resample_cfg.rate_hz)
    if (isinstance(rate, bool) or not isinstance(rate, int | float)
            or abs(rate) > RESAMPLE_RANGES["rate_hz"][1]  # (an int beyond float's range too)
            or not math.isclose(rate, resample_cfg.rate_hz)):
        raise ModelFileError(p, f"rate_hz {repr(rate)[:40]} disagrees with the resample "
                                "settings")
    manifest = _require(p, meta, "arrays", dict)
    if len(manifest) >= MAX_MEMBERS:
        raise ModelFileError(p, f"the manifest lists {len(manifest)} arrays, more than "
                                f"{MAX_MEMBERS - 1}")
    for name, shape in manifest.items():
        problem = _shape_problem(shape)
        if problem is not None:
            raise ModelFileError(p, f"manifest entry {name!r}: {problem}")
    return kind_name, features, resample_cfg, manifest


def load_model(path: str | os.PathLike[str], kind: str | None = None) -> MotionModel:
    """Read and validate a model file (in the order of the module docstring).

    Args:
        path: the .npz written by :func:`save_model`.
        kind: if given, the file must hold a model of this kind.

    Raises:
        ModelFileError: naming the file and the problem (missing, not a regular file, too
            large, not an .npz, truncated, a member's header out of range, metadata not
            bounded JSON, wrong format or version, unknown or unexpected kind, a setting
            out of its range, missing, unexpected, mis-shaped, non-finite or out-of-range
            arrays, invalid model).
    """
    p = Path(path)
    with _open_npz(p) as (zf, members):
        text = str(_read_data(p, zf, members.pop(META_KEY), META_KEY)[()])
        try:
            meta = loads_bounded(text)
        except ValueError as exc:
            raise ModelFileError(p, f"metadata is not valid JSON: {exc}") from exc
        kind_name, features, resample_cfg, manifest = _check_meta(p, meta, kind)
        missing = sorted(set(manifest) - set(members))
        if missing:
            raise ModelFileError(p, f"missing array(s) {', '.join(map(repr, missing))}")
        extra = sorted(set(members) - set(manifest))
        if extra:
            raise ModelFileError(p, f"unexpected array(s) {', '.join(map(repr, extra))}")
        for name, member in members.items():
            if list(member.shape) != manifest[name]:
                raise ModelFileError(
                    p, f"array {name!r} has shape {list(member.shape)}, the manifest says "
                       f"{manifest[name]!r}")
        arrays = {name: _read_data(p, zf, member, name) for name, member in members.items()}
    for name, arr in arrays.items():
        problem = _value_problem(name, arr)
        if problem is not None:
            raise ModelFileError(p, f"array {name!r} {problem}")
    try:
        model_kind = get_kind(kind_name)
    except KeyError:
        raise ModelFileError(
            p, f"unknown model kind {kind_name!r} (known: {', '.join(registered_kinds())})"
        ) from None
    params = meta.get("kind_params", {})
    if not isinstance(params, dict):
        raise ModelFileError(p, "metadata 'kind_params' is not an object")
    try:
        v_model, w_model = model_kind.from_arrays(arrays, params, features)
    except (ValueError, KeyError, TypeError, IndexError) as exc:
        raise ModelFileError(p, f"invalid {kind_name!r} model: {exc}") from exc
    user_meta = meta.get("meta", {})
    if not isinstance(user_meta, dict):
        raise ModelFileError(p, "metadata 'meta' is not an object")
    try:
        calibration = VarianceCalibration.from_dict(
            meta.get("calibration", VarianceCalibration().to_dict()))
    except CalibrationError as exc:
        raise ModelFileError(p, str(exc)) from None
    model = MotionModel(kind=kind_name, feature_config=features, resample_config=resample_cfg,
                        channels=(v_model, w_model), meta=user_meta, calibration=calibration)
    # every array is one the model is made of, of its type (not one the manifest merely
    # lists, nor a bool where a number goes)
    canonical = model_kind.to_arrays(model)[0]
    extra = sorted(set(arrays) - set(canonical))
    if extra:
        raise ModelFileError(p, f"array(s) {', '.join(map(repr, extra))} belong to no part "
                                f"of a {kind_name!r} model")
    for name, arr in arrays.items():
        want = np.asarray(canonical[name]).dtype
        if arr.dtype.kind != want.kind:
            raise ModelFileError(p, f"array {name!r} has dtype {arr.dtype}, a {kind_name!r} "
                                    f"model stores {want}")
    problem = probe_problem(model)
    if problem is not None:
        raise ModelFileError(p, f"not a wheelchair's model: {problem}")
    return model


def probe_problem(model: MotionModel) -> str | None:
    """Why a model cannot be a wheelchair's (None: it may be one): from rest, with the
    joystick held at its centre, at each end of each axis and at a corner for 2 s, it must
    predict speeds, yaw rates and variances within the physical limits (a hostile file
    predicted 1e6 m/s from values each within its array's range)."""
    from asgp_ros.core.rollout import rollout

    s = model.lags
    k = max(1, round(2.0 * model.resample_config.rate_hz))
    held = np.array([(0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0),
                     (1.0, 1.0)])
    future = np.repeat(held[:, None, :], k, axis=1)
    try:
        with np.errstate(all="ignore"):
            out = rollout(model, np.zeros((s, 2)), np.zeros((s, 2)), future)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        return f"it does not predict from rest ({exc})"
    problem = out.problem()
    if problem is None and not model.calibration.is_identity:
        problem = _calibration_shrink_problem(model, future)
    return problem


#: The most a variance calibration may shrink the variance the model itself predicts, in
#: any channel and speed regime: a fitted map corrects an under-estimate (FITC's), so a
#: map that claims a thousandth of the model's variance is a damaged or hostile file (a
#: scale of 0 drew every ellipse as a point while the chair drove at 0.5 m/s, and the
#: shared-control layer reads those covariances as contact probabilities).
MAX_CALIBRATION_SHRINK = 1e3


def _calibration_shrink_problem(model: MotionModel, future: np.ndarray) -> str | None:
    """Why the model's variance calibration claims a certainty the model does not have
    (:data:`MAX_CALIBRATION_SHRINK`), or None: the map applied, in each of its speed
    regimes, to the one-step variances the model predicts over the probe's rollouts (the
    regimes a probe from rest would not reach are checked too)."""
    import dataclasses

    from asgp_ros.core.rollout import rollout

    s = model.lags
    raw_model = dataclasses.replace(model, calibration=VarianceCalibration())
    try:
        with np.errstate(all="ignore"):
            raw = rollout(raw_model, np.zeros((s, 2)), np.zeros((s, 2)), future)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        return f"it does not predict from rest without its calibration ({exc})"
    var = np.diagonal(raw.vel_cov, axis1=-2, axis2=-1).reshape(-1, 2)
    var = var[np.all(np.isfinite(var) & (var > 0.0), axis=1)]
    if var.size == 0:
        return None  # the model predicts no variance: the map changes nothing
    cal = model.calibration
    scale, floor = np.asarray(cal.scale), np.asarray(cal.floor)
    for regime, factor in enumerate(cal.speed_factors):
        with np.errstate(divide="ignore"):
            shrink = var / ((var * scale + floor) * factor)  # inf where it erases it
        worst = float(np.max(shrink))
        if not worst <= MAX_CALIBRATION_SHRINK:
            channel = CHANNELS[int(np.argmax(np.max(shrink, axis=0)))]
            where = f" in speed regime {regime}" if len(cal.speed_factors) > 1 else ""
            how = ("erases the predicted variance of " + channel + where
                   if math.isinf(worst) else
                   f"shrinks the predicted variance of {channel}{where} {worst:.3g}-fold "
                   f"(at most {MAX_CALIBRATION_SHRINK:g})")
            return f"its variance calibration {how}: it would claim a certainty the model " \
                   "does not have"
    return None
