"""The model file: round trip, validation of every corruption, atomic writes."""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from asgp_ros.core import modelfile
from asgp_ros.core.calibration import VarianceCalibration
from asgp_ros.core.features import FeatureConfig, design_matrix
from asgp_ros.core.modelfile import ModelFileError, load_model, save_model
from asgp_ros.core.models import ModelKind, MotionModel, register_kind
from asgp_ros.core.resample import ResampleConfig, Resampled
from asgp_ros.core.rollout import rollout
from asgp_ros.core.sparse_gp import SparseGP


def resampled(T: int = 600, seed: int = 0) -> Resampled:
    rng = np.random.default_rng(seed)
    joy = np.clip(np.cumsum(rng.normal(0, 0.1, (T, 2)), axis=0) * 0.3, -1, 1)
    vel = np.zeros((T, 2))
    for t in range(1, T):
        vel[t] = 0.7 * vel[t - 1] + 0.4 * np.tanh(1.5 * joy[t]) + rng.normal(0, 0.02, 2)
    ok = np.ones(T, dtype=bool)
    no = np.zeros(T, dtype=bool)
    return Resampled(t=np.arange(T) / 5.0, k=np.arange(T, dtype=np.int64), joy=joy, vel=vel,
                     valid=ok, stale=no, tracking_lost=no, gap=no,
                     segment=np.zeros(T, dtype=np.int64), truth=np.full((T, 5), np.nan),
                     truth_valid=no, rate_hz=5.0)


@pytest.fixture(scope="module")
def model() -> MotionModel:
    res = resampled()
    fc = FeatureConfig(lags=3)
    gps = []
    for c in range(2):
        X, y, _ = design_matrix(res, c, fc)
        gps.append(SparseGP(num_inducing=8, seed=0).fit(X, y, max_iter=30))
    return MotionModel("asgp", fc, ResampleConfig(rate_hz=5.0, max_gap_vel_s=0.8),
                       (gps[0], gps[1]), meta={"train": {"bags": ["a.mcap"], "rows": 597}})


@pytest.fixture()
def saved(model: MotionModel, tmp_path: Path) -> Path:
    path = tmp_path / "chair.npz"
    save_model(path, model)
    return path


def rewrite(path: Path, edit: Callable[[dict[str, np.ndarray]], None]) -> None:
    """Load every entry of an .npz, let ``edit`` change the dict, write it back."""
    with np.load(path, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    edit(arrays)
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def edit_meta(change: Callable[[dict[str, Any]], None]) -> Callable[[dict[str, np.ndarray]],
                                                                      None]:
    def edit(arrays: dict[str, np.ndarray]) -> None:
        meta = json.loads(str(arrays["__meta__"][()]))
        change(meta)
        arrays["__meta__"] = np.array(json.dumps(meta))
    return edit


def expect_error(path: Path, match: str, **kwargs: Any) -> ModelFileError:
    with pytest.raises(ModelFileError, match=match) as info:
        load_model(path, **kwargs)
    assert str(path) in str(info.value)
    assert info.value.path == str(path)
    return info.value


def test_round_trip_gives_identical_predictions(model: MotionModel, saved: Path) -> None:
    loaded = load_model(saved, kind="asgp")
    assert loaded.kind == "asgp"
    assert loaded.feature_config == model.feature_config
    assert loaded.resample_config == model.resample_config
    assert loaded.meta == model.meta
    rng = np.random.default_rng(1)
    X = rng.normal(size=(50, model.feature_config.input_dim))
    for a, b in zip(model.channels, loaded.channels, strict=True):
        for ma, mb in zip(a.predict_with_grad(X), b.predict_with_grad(X), strict=True):
            np.testing.assert_array_equal(ma, mb)
    jp, vp, jf = rng.normal(size=(3, 2)), rng.normal(size=(3, 2)), rng.normal(size=(4, 10, 2))
    ra, rb = rollout(model, jp, vp, jf), rollout(loaded, jp, vp, jf)
    np.testing.assert_array_equal(ra.pose, rb.pose)
    np.testing.assert_array_equal(ra.pos_cov, rb.pos_cov)


def test_metadata_is_plain_json(saved: Path) -> None:
    with np.load(saved, allow_pickle=False) as data:
        meta = json.loads(str(data["__meta__"][()]))
        names = set(data.files)
    assert meta["format"] == "asgp_ros.motion_model"
    assert meta["format_version"] == modelfile.FORMAT_VERSION
    assert meta["kind"] == "asgp" and meta["channels"] == ["v", "omega"]
    assert meta["features"] == {"lags": 3, "coupled": False}
    assert meta["rate_hz"] == 5.0 and meta["resample"]["max_gap_vel_s"] == 0.8
    assert meta["meta"]["train"]["rows"] == 597
    assert "normalisation" in meta
    assert set(meta["arrays"]) | {"__meta__"} == names
    assert meta["arrays"]["v.alpha"] == [8]


def test_missing_file_and_directory(tmp_path: Path) -> None:
    expect_error(tmp_path / "nope.npz", "no such file")
    expect_error(tmp_path, "directory")


def test_not_an_npz(tmp_path: Path) -> None:
    path = tmp_path / "model.npz"
    path.write_bytes(b"this is not a zip archive at all\n" * 10)
    expect_error(path, "not an .npz")
    path.write_bytes(b"")
    expect_error(path, "not an .npz")
    np.save(tmp_path / "plain.npy", np.zeros(3))
    expect_error(tmp_path / "plain.npy", "single .npy")


@pytest.mark.parametrize("fraction", [0.3, 0.7, 0.98])
def test_truncated(saved: Path, fraction: float) -> None:
    data = saved.read_bytes()
    saved.write_bytes(data[: int(len(data) * fraction)])
    expect_error(saved, "truncated|not an .npz")


def test_corrupted_member(saved: Path) -> None:
    """A flipped bit inside an array's data is caught by the archive's CRC-32."""
    with zipfile.ZipFile(saved) as zf:
        info = zf.getinfo("omega.var_matrix.npy")
    data = bytearray(saved.read_bytes())
    off = info.header_offset  # local header: name and extra lengths at bytes 26 and 28
    start = off + 30 + int.from_bytes(data[off + 26:off + 28], "little") + int.from_bytes(
        data[off + 28:off + 30], "little")
    assert data[start:start + 6] == b"\x93NUMPY"
    data[start + 128 + 8 * 5] ^= 0x01  # a mantissa bit of one matrix entry
    saved.write_bytes(bytes(data))
    expect_error(saved, "omega.var_matrix.*cannot be read.*CRC")


def test_wrong_version(saved: Path) -> None:
    rewrite(saved, edit_meta(lambda m: m.update(format_version=2)))
    expect_error(saved, "format version 2 .*newer.* reads 1")
    rewrite(saved, edit_meta(lambda m: m.update(format_version="1")))
    expect_error(saved, "format_version")


def test_wrong_format_name(saved: Path) -> None:
    rewrite(saved, edit_meta(lambda m: m.update(format="something.else")))
    expect_error(saved, "not an asgp_ros model file")


def test_unknown_and_unexpected_kind(saved: Path) -> None:
    expect_error(saved, "holds a 'asgp' model, expected 'mlp'", kind="mlp")
    rewrite(saved, edit_meta(lambda m: m.update(kind="quantum")))
    expect_error(saved, "unknown model kind 'quantum'")


def test_missing_unexpected_and_misshaped_arrays(saved: Path) -> None:
    original = saved.read_bytes()
    rewrite(saved, lambda a: a.pop("omega.alpha"))
    expect_error(saved, "missing array.*omega.alpha")
    saved.write_bytes(original)
    rewrite(saved, lambda a: a.update(extra=np.zeros(2)))
    expect_error(saved, "unexpected array.*extra")
    saved.write_bytes(original)
    rewrite(saved, lambda a: a.update({"v.alpha": np.zeros(9)}))
    expect_error(saved, "v.alpha.*shape \\[9\\].*manifest")

    # a consistent manifest, but the kind's own check sees the shape is wrong
    def shrink(a: dict[str, np.ndarray]) -> None:
        a["v.alpha"] = np.zeros(9)
        edit_meta(lambda m: m["arrays"].update({"v.alpha": [9]}))(a)

    saved.write_bytes(original)
    rewrite(saved, shrink)
    expect_error(saved, "invalid 'asgp' model.*alpha")


def test_wrong_lags_for_the_arrays(saved: Path) -> None:
    rewrite(saved, edit_meta(lambda m: m.update(features={"lags": 5, "coupled": False})))
    expect_error(saved, "7 columns but lags=5")


def test_non_finite_values(saved: Path) -> None:
    def poison(a: dict[str, np.ndarray]) -> None:
        a["omega.var_matrix"] = a["omega.var_matrix"].copy()
        a["omega.var_matrix"][1, 2] = np.nan

    rewrite(saved, poison)
    expect_error(saved, "omega.var_matrix.*NaN or inf")


def test_metadata_problems(saved: Path) -> None:
    original = saved.read_bytes()
    rewrite(saved, lambda a: a.update(__meta__=np.array("{not json")))
    expect_error(saved, "not valid JSON")
    saved.write_bytes(original)
    rewrite(saved, lambda a: a.update(__meta__=np.array("[1, 2]")))
    expect_error(saved, "not a JSON object")
    saved.write_bytes(original)
    rewrite(saved, lambda a: a.update(__meta__=np.frombuffer(b"{}", dtype=np.uint8)))
    expect_error(saved, "not a JSON string")
    saved.write_bytes(original)
    rewrite(saved, lambda a: a.pop("__meta__"))
    expect_error(saved, "no metadata")
    saved.write_bytes(original)
    rewrite(saved, edit_meta(lambda m: m.update(features={"lags": 0})))
    expect_error(saved, "invalid settings.*lags")
    saved.write_bytes(original)
    rewrite(saved, edit_meta(lambda m: m.pop("arrays")))
    expect_error(saved, "lacks 'arrays'")


def test_pickled_object_arrays_are_refused(saved: Path) -> None:
    with np.load(saved, allow_pickle=False) as data:
        arrays: dict[str, Any] = {name: data[name] for name in data.files}
    arrays["v.alpha"] = np.array([{"evil": 1}], dtype=object)
    with open(saved, "wb") as fh:
        np.savez(fh, **arrays)
    expect_error(saved, "v.alpha.*cannot be read")


def test_failed_save_leaves_the_existing_file_intact(model: MotionModel, saved: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    before = saved.read_bytes()

    def half_written(fh: Any, **arrays: Any) -> None:
        fh.write(b"PK\x03\x04 partial")
        raise OSError("disk full")

    monkeypatch.setattr(modelfile.np, "savez", half_written)
    with pytest.raises(OSError, match="disk full"):
        save_model(saved, model)
    monkeypatch.undo()
    assert saved.read_bytes() == before
    assert sorted(os.listdir(saved.parent)) == [saved.name]  # no temporaries left
    load_model(saved)


def test_save_refuses_bad_models(model: MotionModel, tmp_path: Path) -> None:
    path = tmp_path / "m.npz"
    bad_meta = MotionModel("asgp", model.feature_config, model.resample_config,
                           model.channels, meta={"x": float("nan")})
    with pytest.raises(ModelFileError, match="JSON"):
        save_model(path, bad_meta)
    unknown = MotionModel("nosuchkind", model.feature_config, model.resample_config,
                          model.channels)
    with pytest.raises(ModelFileError, match="unknown model kind"):
        save_model(path, unknown)
    assert not path.exists()
    assert os.listdir(tmp_path) == []


class ScaleChannel:
    """A registered stand-in kind: mean = a . x, variance 0."""

    def __init__(self, a: np.ndarray) -> None:
        self.a = a

    def predict(self, X: np.ndarray, include_noise: bool = True
                ) -> tuple[np.ndarray, np.ndarray]:
        return X @ self.a, np.zeros(X.shape[0])

    def predict_with_grad(self, X: np.ndarray, include_noise: bool = True
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        m, v = self.predict(X)
        return m, v, np.tile(self.a, (X.shape[0], 1))


def test_registered_kinds_use_the_same_file_format(tmp_path: Path) -> None:
    def to_arrays(m: MotionModel) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        return ({f"{n}.a": ch.a for n, ch in zip(("v", "omega"), m.channels, strict=True)},
                {"note": "linear"})

    def from_arrays(arrays: Mapping[str, np.ndarray], params: Mapping[str, Any],
                    features: FeatureConfig) -> tuple[ScaleChannel, ScaleChannel]:
        assert params == {"note": "linear"}
        if arrays["v.a"].shape != (features.input_dim,):
            raise ValueError(f"v.a must have {features.input_dim} entries")
        return ScaleChannel(arrays["v.a"]), ScaleChannel(arrays["omega.a"])

    register_kind(ModelKind("test_scale", to_arrays, from_arrays), replace=True)
    fc = FeatureConfig(lags=2)
    m = MotionModel("test_scale", fc, ResampleConfig(),
                    (ScaleChannel(0.01 * np.arange(5.0)), ScaleChannel(-0.01 * np.arange(5.0))))
    path = tmp_path / "scale.model"  # any suffix: nothing is appended
    save_model(path, m)
    assert os.listdir(tmp_path) == ["scale.model"]
    loaded = load_model(path, kind="test_scale")
    np.testing.assert_allclose(loaded.channels[1].predict(np.ones((1, 5)))[0], [-0.1])
    rewrite(path, edit_meta(lambda meta: meta.update(features={"lags": 3, "coupled": False})))
    expect_error(path, "invalid 'test_scale' model: v.a must have 7 entries")
    with pytest.raises(ValueError, match="already registered"):
        register_kind(ModelKind("test_scale", to_arrays, from_arrays))


# ---- untrusted files: every size and number is checked before it is used ---------------

def _replace_member(path: Path, member: str, payload: bytes) -> None:
    """Rewrite the archive with ``member``'s bytes replaced by ``payload`` (others kept)."""
    with zipfile.ZipFile(path) as zf:
        entries = [(info.filename, zf.read(info)) for info in zf.infolist()]
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in entries:
            zf.writestr(name, payload if name == member else data)


def _npy(shape: tuple[int, ...], dtype: str, data: bytes) -> bytes:
    """An .npy member whose header declares ``shape`` whatever ``data`` holds."""
    import io

    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        buf, {"descr": np.dtype(dtype).str, "fortran_order": False, "shape": shape})
    return buf.getvalue() + data


def _run_with_deadline(code: str, deadline_s: float = 20.0) -> Any:
    import subprocess
    import sys

    try:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=deadline_s, check=False)
    except subprocess.TimeoutExpired:
        pytest.fail(f"hung for {deadline_s} s: {code}")


def test_a_header_declaring_a_huge_shape_allocates_nothing(saved: Path) -> None:
    """Issue 16: a header with shape 10**10 made np.load allocate 80 GB (MemoryError)."""
    _replace_member(saved, "v.alpha.npy", _npy((10**10,), "<f8", np.zeros(8).tobytes()))
    proc = _run_with_deadline(
        "import resource, sys\n"
        "resource.setrlimit(resource.RLIMIT_AS, (2 * 2**30, 2 * 2**30))\n"
        "from asgp_ros.core.modelfile import ModelFileError, load_model\n"
        f"try:\n    load_model({str(saved)!r})\n"
        "except ModelFileError as exc:\n    print(exc)\n")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert str(saved) in proc.stdout and "'v.alpha'" in proc.stdout
    assert "10000000000" in proc.stdout and "MemoryError" not in proc.stderr
    expect_error(saved, r"array 'v.alpha' cannot be read: its header's shape \[10000000000\]")


def test_headers_must_match_the_data_they_hold(saved: Path) -> None:
    original = saved.read_bytes()
    _replace_member(saved, "v.alpha.npy", _npy((100,), "<f8", np.zeros(8).tobytes()))
    expect_error(saved, "'v.alpha' cannot be read: its header declares 800 data bytes, "
                        "the archive holds 64")
    saved.write_bytes(original)
    _replace_member(saved, "v.alpha.npy", _npy((2, 2, 2, 1, 1), "<f8", np.zeros(8).tobytes()))
    expect_error(saved, "'v.alpha'.*more than 4 dimensions")
    saved.write_bytes(original)
    _replace_member(saved, "v.alpha.npy", _npy((8,), "<c16", np.zeros(16).tobytes()))
    expect_error(saved, "'v.alpha' cannot be read: non-numeric dtype complex128")


def test_a_manifest_with_absurd_shapes_is_refused(saved: Path) -> None:
    original = saved.read_bytes()
    for shape, match in (([10**10], "size outside"), ([-1], "size outside"),
                         ([True], "size outside"), ([4096, 4096], "more than 4194304"),
                         ("8", "not a list")):
        saved.write_bytes(original)
        rewrite(saved, edit_meta(lambda m, s=shape: m["arrays"].update({"v.alpha": s})))
        expect_error(saved, f"manifest entry 'v.alpha': .*{match}")


def test_deeply_nested_metadata_is_refused_without_recursing(saved: Path) -> None:
    """Issue 16: deeply nested JSON metadata raised RecursionError."""
    original = saved.read_bytes()
    deep = "[" * 100_000 + "]" * 100_000
    rewrite(saved, edit_meta(lambda m: m.update(meta={"x": "__DEEP__"})))
    rewrite(saved, lambda a: a.update(__meta__=np.array(
        str(a["__meta__"][()]).replace('"__DEEP__"', deep))))
    expect_error(saved, "metadata is not valid JSON: nested 100002 levels deep, more than "
                        "the limit of 32")
    saved.write_bytes(original)
    # brackets inside strings do not count
    rewrite(saved, edit_meta(lambda m: m.update(meta={"note": "[[[{{{" * 1000})))
    assert load_model(saved).meta["note"].startswith("[[[{{{")


def test_metadata_size_and_numbers_are_bounded(saved: Path) -> None:
    original = saved.read_bytes()
    rewrite(saved, edit_meta(lambda m: m.update(meta={"blob": "x" * (2**20 + 1)})))
    expect_error(saved, "metadata is .*characters, more than the limit of 1048576")
    for literal in ("NaN", "Infinity", "-Infinity", "1e999"):
        saved.write_bytes(original)
        rewrite(saved, edit_meta(lambda m: m.update(meta={"x": "__NUM__"})))
        rewrite(saved, lambda a, lit=literal: a.update(__meta__=np.array(
            str(a["__meta__"][()]).replace('"__NUM__"', lit))))
        expect_error(saved, "metadata is not valid JSON: .*(finite|beyond the range)")


@pytest.mark.parametrize(("field", "value"), [
    ("rate_hz", 1e300), ("rate_hz", 1e20), ("rate_hz", 1e-300), ("max_gap_vel_s", 1e300),
    ("stale_tolerance", 10.0), ("stale_joy_threshold", 2.0),
])
def test_resample_settings_out_of_range_are_refused(saved: Path, field: str,
                                                    value: float) -> None:
    """Issue 16: a file with rate_hz 1e300 loaded, then hung Predictor.predict."""
    def change(m: dict[str, Any]) -> None:
        m["resample"][field] = value
        if field == "rate_hz":
            m["rate_hz"] = value

    rewrite(saved, edit_meta(change))
    expect_error(saved, f"invalid settings: {field} must be in")


@pytest.mark.parametrize("where", ["resample.stale_after_s", "resample.rate_hz", "rate_hz",
                                   "calibration.scale", "calibration.speed_factors"])
@pytest.mark.parametrize("sign", [1, -1])
def test_an_integer_beyond_floats_range_is_refused(saved: Path, where: str, sign: int) -> None:
    """JSON holds integers of any size: 10**400 in a setting raised OverflowError with a
    traceback (benchmarks/fuzz.py, seed 7373, in resample.stale_after_s; the same in
    rate_hz and the calibration)."""
    huge = sign * 10**400

    def change(m: dict[str, Any]) -> None:
        section, _, key = where.rpartition(".")
        target = m[section] if section else m
        target[key] = [huge, 1.0] if key == "scale" else [huge] if key == "speed_factors" \
            else huge

    rewrite(saved, edit_meta(change))
    err = expect_error(saved, "must be in|must hold numbers|disagrees with|beyond 64 bits")
    assert "\n" not in str(err) and len(str(err)) < 2000


@pytest.mark.parametrize("value", ["end", "", None, 1, ["midpoint"], "MIDPOINT"])
def test_an_unknown_vo_stamp_convention_is_refused(saved: Path, value: object) -> None:
    rewrite(saved, edit_meta(lambda m: m["resample"].update(vel_stamp=value)))
    expect_error(saved, "invalid settings: vel_stamp must be one of")


def test_a_file_without_the_vo_stamp_setting_reads_the_stamps_as_recorded(saved: Path
                                                                        ) -> None:
    assert load_model(saved).resample_config.vel_stamp == "midpoint"
    rewrite(saved, edit_meta(lambda m: m["resample"].pop("vel_stamp")))
    assert load_model(saved).resample_config.vel_stamp == "frame"


def test_top_level_rate_must_be_a_number(saved: Path) -> None:
    rewrite(saved, edit_meta(lambda m: m.update(rate_hz=True)))
    expect_error(saved, "rate_hz True disagrees")


def test_lags_out_of_range_are_refused(saved: Path) -> None:
    rewrite(saved, edit_meta(lambda m: m.update(features={"lags": 10**9, "coupled": False})))
    expect_error(saved, r"invalid settings: lags must be in \[1, 1000\]")


@pytest.mark.parametrize(("name", "value", "match"), [
    ("v.x_scale", 0.0, r"normalisation entry 0 = 0 is outside \[1e-12, 1e\+06\]"),
    ("omega.y_scale", 1e9, r"normalisation entry 0 = 1e\+09 is outside"),
    ("v.x_mean", -1e7, r"normalisation entry 0 = -1e\+07 is outside"),
    ("v.var_matrix", 1e200, r"has a value beyond \+-1e\+15"),
])
def test_array_values_out_of_range_are_refused(saved: Path, name: str, value: float,
                                               match: str) -> None:
    def poison(a: dict[str, np.ndarray]) -> None:
        arr = a[name].copy()
        arr.reshape(-1)[0] = value
        a[name] = arr

    rewrite(saved, poison)
    expect_error(saved, f"array '{name}' {match}")


def test_mlp_normalisation_is_checked_per_entry(tmp_path: Path) -> None:
    from asgp_ros.core.baselines import MLPChannel

    rng = np.random.default_rng(0)
    fc = FeatureConfig(lags=2)
    chans = [MLPChannel([rng.normal(size=(5, 3)), rng.normal(size=(3, 1))],
                        [np.zeros(3), np.zeros(1)], np.zeros(5), np.ones(5), 0.1, 0.5)
             for _ in range(2)]
    path = tmp_path / "mlp.npz"
    save_model(path, MotionModel("mlp", fc, ResampleConfig(), (chans[0], chans[1])))
    assert load_model(path).kind == "mlp"
    rewrite(path, lambda a: a.update({"omega.y_norm": np.array([0.1, -2.0])}))
    expect_error(path, r"array 'omega.y_norm' normalisation entry 1 = -2 is outside")


def test_save_refuses_what_load_would_refuse(model: MotionModel, tmp_path: Path) -> None:
    from asgp_ros.core import models

    arrays, _params = models.get_kind("asgp").to_arrays(model)
    arrays["v.x_scale"] = np.full_like(arrays["v.x_scale"], 1e9)
    with pytest.raises(ModelFileError, match=r"'v\.x_scale' normalisation entry 0"):
        modelfile._check_arrays(tmp_path / "m.npz", arrays)


def test_a_fifo_is_refused_at_once(tmp_path: Path) -> None:
    """Issue 16: a model path that is a FIFO blocked the reader (and the node) forever."""
    fifo = tmp_path / "model.npz"
    os.mkfifo(fifo)
    proc = _run_with_deadline(
        "from asgp_ros.core.modelfile import ModelFileError, load_model\n"
        f"try:\n    load_model({str(fifo)!r})\n"
        "except ModelFileError as exc:\n    print(exc)\n")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == f"model file {fifo}: is a FIFO (named pipe), not a regular file"
    link = tmp_path / "link.npz"
    link.symlink_to(fifo)
    expect_error(link, "is a FIFO")


def test_devices_sockets_and_oversized_files_are_refused(tmp_path: Path) -> None:
    import socket

    if os.path.exists("/dev/zero"):
        with pytest.raises(ModelFileError, match="/dev/zero: is a character device"):
            load_model("/dev/zero")
    sock_path = tmp_path / "s.npz"
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(sock_path))
        expect_error(sock_path, "is a socket, not a regular file")
    big = tmp_path / "big.npz"
    with open(big, "wb") as fh:
        fh.truncate(modelfile.MAX_FILE_BYTES + 1)  # sparse: no disk used
    expect_error(big, f"is {modelfile.MAX_FILE_BYTES + 1} bytes, more than the limit")


def test_a_forged_member_count_is_refused_before_parsing(saved: Path) -> None:
    data = bytearray(saved.read_bytes())
    at = data.rfind(b"PK\x05\x06")
    data[at + 8:at + 12] = (60000).to_bytes(2, "little") * 2
    saved.write_bytes(bytes(data))
    expect_error(saved, "60000 members, more than 256")


def test_loads_bounded_directly() -> None:
    assert modelfile.loads_bounded('{"a": [1, 2.5, "]]]"]}') == {"a": [1, 2.5, "]]]"]}
    with pytest.raises(ValueError, match="nested 3 levels"):
        modelfile.loads_bounded("[[[1]]]", max_depth=2)
    with pytest.raises(ValueError, match="more than the limit of 4"):
        modelfile.loads_bounded("[1, 2]", max_chars=4)


def test_save_refuses_metadata_that_load_would_refuse(model: MotionModel,
                                                      tmp_path: Path) -> None:
    nested: dict[str, Any] = {}
    inner = nested
    for _ in range(40):
        inner["x"] = {}
        inner = inner["x"]
    deep = MotionModel("asgp", model.feature_config, model.resample_config, model.channels,
                       meta=nested)
    with pytest.raises(ModelFileError, match=r"metadata cannot be stored: nested 4\d levels"):
        save_model(tmp_path / "m.npz", deep)
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("header", [
    b"{'descr': '<f8', 'fortran_order': False, 'shape': (8,",  # never closed
    b"{'descr': '<f8', 'fortran_order': False, 'shape': (8,), 'x': __import__('os')}",
    b"not a dict at all",
])
def test_a_malformed_npy_header_is_a_model_file_error(saved: Path, header: bytes) -> None:
    text = header + b" " * (127 - 10 - len(header) % 64) + b"\n"
    member = b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text
    _replace_member(saved, "v.alpha.npy", member + np.zeros(8).tobytes())
    expect_error(saved, "array 'v.alpha' cannot be read \\(truncated or corrupt header")


# ---- hostile values that each pass their array's range (an attack on the loader) --------

def _scaled(name: str, value: float) -> Callable[[dict[str, np.ndarray]], None]:
    def edit(arrays: dict[str, np.ndarray]) -> None:
        arrays[name] = np.full_like(arrays[name], value)
    return edit


@pytest.mark.parametrize("name, value", [("v.y_mean", 1e6), ("v.alpha", 1e12),
                                         ("omega.alpha", -1e12)])
def test_a_model_that_drives_a_chair_at_rest_beyond_physics_is_refused(
        saved: Path, name: str, value: float) -> None:
    """Each value within its array's range, the model predicted 1e6 m/s from rest with the
    stick held: such a file is no wheelchair's model, and is refused at load."""
    rewrite(saved, _scaled(name, value))
    expect_error(saved, "not a wheelchair's model: the model predicted")


@pytest.mark.parametrize("value", [1e15, 1e-300])
def test_a_noise_variance_out_of_range_is_refused_by_name(saved: Path, value: float) -> None:
    rewrite(saved, _scaled("v.noise_variance", value))
    expect_error(saved, "noise_variance")


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_a_variance_matrix_that_is_no_posterior_is_refused(saved: Path, sign: float) -> None:
    """Without its Cholesky factor (older files), a var_matrix of +-1e12 I loaded: the
    latent variance was clipped to 0 (over-confident ellipses) or huge."""
    def edit(arrays: dict[str, np.ndarray]) -> None:
        M = arrays["v.var_matrix"].shape[0]
        arrays["v.var_matrix"] = sign * 1e12 * np.eye(M)
        del arrays["v.chol_a"]
        meta = json.loads(str(arrays["__meta__"][()]))
        del meta["arrays"]["v.chol_a"]
        arrays["__meta__"] = np.array(json.dumps(meta))
    rewrite(saved, edit)
    expect_error(saved, "var_matrix")


def test_an_array_of_no_part_of_the_model_is_refused(saved: Path) -> None:
    """An array the manifest lists but the model is not made of ('zz', 'v.extra') loaded."""
    for name in ("zz", "v.extra"):
        def edit(arrays: dict[str, np.ndarray], name: str = name) -> None:
            arrays[name] = np.zeros(3)
            meta = json.loads(str(arrays["__meta__"][()]))
            meta["arrays"][name] = [3]
            arrays["__meta__"] = np.array(json.dumps(meta))
        rewrite(saved, edit)
        expect_error(saved, f"{name!r} belong to no part")
        rewrite(saved, lambda a, name=name: _forget(a, name))


def _forget(arrays: dict[str, np.ndarray], name: str) -> None:
    del arrays[name]
    meta = json.loads(str(arrays["__meta__"][()]))
    del meta["arrays"][name]
    arrays["__meta__"] = np.array(json.dumps(meta))


def test_a_bool_where_a_number_goes_and_a_negative_count_are_refused(saved: Path) -> None:
    rewrite(saved, lambda a: a.update({"v.y_scale": np.asarray(True)}))
    expect_error(saved, "'v.y_scale' has dtype bool")
    rewrite(saved, lambda a: a.update({"v.y_scale": np.asarray(1.0)}))
    rewrite(saved, _scaled("v.num_data", -5.0))
    expect_error(saved, "num_data")


def test_an_integer_beyond_64_bits_anywhere_in_the_metadata_is_refused(saved: Path) -> None:
    """The free record (what training wrote, read by ``asgp info``) too: 10**400 there
    raised OverflowError with a traceback in ``asgp info``."""
    rewrite(saved, edit_meta(lambda m: m["meta"].update(training_data={"duration_s":
                                                                       10**400})))
    err = expect_error(saved, "beyond 64 bits")
    assert "\n" not in str(err)


def test_a_model_files_strings_cannot_forge_lines_of_asgp_info(tmp_path, capsys):
    """A newline or a terminal escape in a model file's metadata printed a second, false
    'variance calibration:' line (and the escape went to the terminal)."""
    import dataclasses

    from asgp_ros.cli import main
    from asgp_ros.core.modelfile import load_model, save_model

    repo = Path(__file__).resolve().parents[1]
    model = load_model(repo / "docs" / "reproduction" / "models" / "tile_asgp_paper.npz")
    meta = dict(model.meta)
    meta["training"] = {**meta["training"], "configuration":
                        "automatic\nvariance calibration: calibrated, 95.0%\x1b[2K"}
    forged = tmp_path / "forged.npz"
    save_model(forged, dataclasses.replace(model, meta=meta))
    assert main(["info", str(forged)]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out
    assert sum(line.startswith("variance calibration:") for line in out.splitlines()) == 1


@pytest.mark.parametrize(("cal", "match"), [
    ({"scale": [0.0, 0.0], "floor": [0.0, 0.0]}, "erases the predicted variance of v"),
    ({"scale": [1.0, 1e-9], "floor": [0.0, 0.0]}, "shrinks the predicted variance of omega"),
    ({"scale": [1e-6, 1e-6], "floor": [0.0, 0.0], "speed_factors": [1e-6]}, "shrinks"),
    # a regime that a probe from rest never reaches (speeds below 0) is checked too
    ({"scale": [1.0, 1.0], "floor": [0.0, 0.0], "speed_edges": [0.0],
      "speed_factors": [1e-6, 1.0]}, "of v in speed regime 0"),
])
def test_a_calibration_claiming_a_certainty_the_model_lacks_is_refused(
        model: MotionModel, saved: Path, cal: dict[str, Any], match: str) -> None:
    """Each number within its range, a calibration of scale 0 loaded and drew every 95 %
    ellipse as a point while the chair drove (the shared-control layer reads them as
    contact probabilities): the map may shrink the model's own variance at most
    MAX_CALIBRATION_SHRINK-fold, in every regime."""
    def change(m: dict[str, Any]) -> None:
        m["calibration"] = {"speed_edges": [], "speed_factors": [1.0], **cal}

    rewrite(saved, edit_meta(change))
    err = expect_error(saved, f"not a wheelchair's model: its variance calibration .*{match}")
    assert "\n" not in str(err)
    with pytest.raises(ModelFileError, match="certainty"):  # nor written
        save_model(saved.parent / "again.npz", dataclasses.replace(
            model, calibration=VarianceCalibration.from_dict(
                {"speed_edges": [], "speed_factors": [1.0], **cal})))


def test_a_calibration_that_shrinks_within_the_bound_or_inflates_loads(
        model: MotionModel, tmp_path: Path) -> None:
    """The bound is on shrinking: a map that inflates (as FITC's under-estimate needs), one
    that shrinks a hundredfold, and one made of a floor alone load and predict with it."""
    for i, cal in enumerate((
            VarianceCalibration(scale=(3.0, 2.0), floor=(1e-4, 1e-4)),
            VarianceCalibration(scale=(0.01, 0.01), floor=(0.0, 0.0)),
            VarianceCalibration(scale=(0.0, 0.0), floor=(1e-3, 1e-3)))):
        path = tmp_path / f"m{i}.npz"
        save_model(path, dataclasses.replace(model, calibration=cal))
        assert load_model(path).calibration == cal
