"""The model file: one ``.npz`` holding a trained two-channel predictor.

Layout (format version 1):

* ``__meta__``: a 0-d unicode array holding one JSON object::

      {"format": "asgp_ros.motion_model", "format_version": 1, "kind": "asgp",
       "channels": ["v", "omega"], "features": {"lags": 4, "coupled": false},
       "resample": {"rate_hz": 5.0, ...}, "rate_hz": 5.0,
       "kind_params": {...}, "normalisation": ..., "meta": {training data summary, ...},
       "arrays": {"v.alpha": [20], ...}}

* one numeric array per entry of ``arrays`` (names ``<channel>.<field>`` by convention),
  as the kind's ``to_arrays`` produced them (:mod:`asgp_ros.core.models`).

The file is written atomically (:func:`asgp_ros.fileio.atomic_path`: a failed save leaves
any previous file untouched) and read with ``np.load(allow_pickle=False)``; nothing in it
is executable. :func:`load_model` validates everything (container, version, kind, the
array manifest, shapes, finiteness, and the kind's own checks) and raises
:class:`ModelFileError` naming the file and the problem.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import zipfile
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from asgp_ros.core.features import CHANNELS, FeatureConfig
from asgp_ros.core.models import MotionModel, get_kind, registered_kinds
from asgp_ros.core.resample import ResampleConfig
from asgp_ros.fileio import atomic_path

logger = logging.getLogger(__name__)

FORMAT_NAME = "asgp_ros.motion_model"
FORMAT_VERSION = 1
META_KEY = "__meta__"
_NAME_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.]{0,127}")
_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error)


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


def _check_arrays(path: str | os.PathLike[str],
                  arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name, value in arrays.items():
        if not isinstance(name, str) or not _NAME_RE.fullmatch(name):
            raise ModelFileError(path, f"array name {name!r} is not allowed")
        arr = np.asarray(value)
        if arr.dtype.kind not in "fiub":
            raise ModelFileError(path, f"array {name!r} has non-numeric dtype {arr.dtype}")
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise ModelFileError(path, f"array {name!r} contains NaN or inf")
        out[name] = arr
    return out


def save_model(path: str | os.PathLike[str], model: MotionModel) -> None:
    """Write ``model`` to ``path`` (one .npz, atomically; see the module docstring).

    Raises:
        ModelFileError: the model cannot be stored (unknown kind, non-finite arrays,
            metadata that is not JSON).
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
        "arrays": {name: list(arr.shape) for name, arr in arrays.items()},
    }
    try:
        text = json.dumps(meta, allow_nan=False, sort_keys=True)
    except (TypeError, ValueError) as exc:
        raise ModelFileError(path, f"metadata is not plain JSON: {exc}") from exc
    payload: dict[str, Any] = {META_KEY: np.array(text), **arrays}
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        # a file object, so numpy does not append ".npz" to the temporary name
        np.savez(fh, **payload)
    logger.info("saved %s model to %s", model.kind, path)


def _read_npz(path: Path) -> tuple[str, dict[str, np.ndarray]]:
    """The metadata text and the arrays of an .npz, or ModelFileError."""
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise ModelFileError(path, "no such file") from None
    except IsADirectoryError:
        raise ModelFileError(path, "is a directory, not a model file") from None
    except _READ_ERRORS as exc:
        raise ModelFileError(
            path, f"not an .npz model file (unreadable or truncated archive: {exc})"
        ) from exc
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ModelFileError(path, "not an .npz model file (a single .npy array)")
    arrays: dict[str, np.ndarray] = {}
    try:
        names = list(data.files)
        if META_KEY not in names:
            raise ModelFileError(path, f"no metadata entry {META_KEY!r} (not a model file)")
        for name in names:
            try:
                arrays[name] = np.asarray(data[name])
            except _READ_ERRORS as exc:
                raise ModelFileError(
                    path, f"array {name!r} cannot be read (truncated or corrupt: {exc})"
                ) from exc
    finally:
        data.close()
    meta_arr = arrays.pop(META_KEY)
    if meta_arr.ndim != 0 or meta_arr.dtype.kind != "U":
        raise ModelFileError(path, f"metadata {META_KEY!r} is not a JSON string")
    return str(meta_arr[()]), arrays


def _require(path: Path, meta: dict[str, Any], key: str, typ: type | tuple[type, ...]) -> Any:
    if key not in meta:
        raise ModelFileError(path, f"metadata lacks {key!r}")
    value = meta[key]
    if not isinstance(value, typ) or (isinstance(value, bool) and typ is not bool):
        raise ModelFileError(path, f"metadata {key!r} has the wrong type ({value!r})")
    return value


def load_model(path: str | os.PathLike[str], kind: str | None = None) -> MotionModel:
    """Read and validate a model file.

    Args:
        path: the .npz written by :func:`save_model`.
        kind: if given, the file must hold a model of this kind.

    Raises:
        ModelFileError: naming the file and the problem (missing, not an .npz, truncated,
            metadata not JSON, wrong format or version, unknown or unexpected kind,
            missing, unexpected, mis-shaped or non-finite arrays, invalid model).
    """
    p = Path(path)
    text, arrays = _read_npz(p)
    try:
        meta = json.loads(text)
    except ValueError as exc:
        raise ModelFileError(p, f"metadata is not valid JSON: {exc}") from exc
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
    try:
        model_kind = get_kind(kind_name)
    except KeyError:
        raise ModelFileError(
            p, f"unknown model kind {kind_name!r} (known: {', '.join(registered_kinds())})"
        ) from None
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
    if not isinstance(rate, int | float) or not math.isclose(rate, resample_cfg.rate_hz):
        raise ModelFileError(p, f"rate_hz {rate!r} disagrees with the resample settings")
    manifest = _require(p, meta, "arrays", dict)
    missing = sorted(set(manifest) - set(arrays))
    if missing:
        raise ModelFileError(p, f"missing array(s) {', '.join(map(repr, missing))}")
    extra = sorted(set(arrays) - set(manifest))
    if extra:
        raise ModelFileError(p, f"unexpected array(s) {', '.join(map(repr, extra))}")
    for name, arr in arrays.items():
        shape = manifest[name]
        if not isinstance(shape, list) or list(arr.shape) != shape:
            raise ModelFileError(
                p, f"array {name!r} has shape {list(arr.shape)}, the manifest says {shape!r}"
            )
        if arr.dtype.kind not in "fiub":
            raise ModelFileError(p, f"array {name!r} has non-numeric dtype {arr.dtype}")
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise ModelFileError(p, f"array {name!r} contains NaN or inf")
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
    return MotionModel(kind=kind_name, feature_config=features, resample_config=resample_cfg,
                       channels=(v_model, w_model), meta=user_meta)
