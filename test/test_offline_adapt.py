"""``asgp adapt`` and :mod:`asgp_ros.learning.adapting`: a trained ASGP brought to another
floor by its recordings, written as a new model file."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from asgp_ros.cli import main
from asgp_ros.core.adapt import AdaptConfig, OnlinePosterior
from asgp_ros.core.modelfile import load_model, save_model
from asgp_ros.core.resample import ResampleConfig, resample
from asgp_ros.core.sparse_gp import SparseGP
from asgp_ros.learning.adapting import AdaptingError, OfflineAdaptOptions, adapt_model
from asgp_ros.learning.evaluation import TestSeries, evaluate_model
from asgp_ros.learning.training import Series, TrainOptions, design, read_series, train

SMALL = TrainOptions(kind="asgp", lags=2, coupled=True, inducing_v=20, inducing_w=20,
                     max_iter=40)


@pytest.fixture(scope="module")
def floors(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Simulated recordings: tile to train on, carpet to adapt to and carpet to test on."""
    out = tmp_path_factory.mktemp("floors")
    bags = {}
    for name, surface, minutes, seed in (("tile", "tile", 4, 11), ("carpet", "carpet", 8, 12),
                                         ("carpet_test", "carpet", 3, 13)):
        bags[name] = out / name
        assert main(["simulate", "--surface", surface, "--minutes", str(minutes), "--seed",
                     str(seed), "--out", str(bags[name]), "--no-truth"]) == 0
    return bags


@pytest.fixture(scope="module")
def tile_model(floors: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("models") / "tile.npz"
    save_model(path, train(read_series([str(floors["tile"])]), SMALL))
    return path


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_adapting_to_another_floor_recovers_success_and_coverage(
        floors: dict[str, Path], tile_model: Path) -> None:
    model = load_model(tile_model)
    adapted = adapt_model(model, read_series([str(floors["carpet"])]))
    test = [TestSeries(s.name, s.res) for s in read_series([str(floors["carpet_test"])])]
    before = evaluate_model(model, test, (1.0, 2.0)).horizons
    after = evaluate_model(adapted, test, (1.0, 2.0)).horizons
    # on fresh recordings of the new floor: better predictions, and honest ellipses
    assert after["2.0"].vo.success_rate > before["2.0"].vo.success_rate + 0.08
    for key in ("1.0", "2.0"):
        assert before[key].vo.coverage_95 < 0.6
        assert 0.85 <= after[key].vo.coverage_95 <= 0.99
    ad = adapted.meta["adaptation"]
    assert ad["calibration"] == "fitted on the held-out part"
    held = ad["held_out"]
    assert held["adapted"]["2.0"]["success"] > held["trained"]["2.0"]["success"]
    # the trained model object is left as it was
    fresh = load_model(tile_model)
    for a, b in zip(model.channels, fresh.channels, strict=True):
        assert np.array_equal(a.posterior.alpha, b.posterior.alpha)
        assert np.array_equal(a.posterior.C, b.posterior.C)
    assert model.calibration == fresh.calibration and "adaptation" not in model.meta


def test_with_the_trained_data_whole_it_is_the_batch_posterior(floors: dict[str, Path]
                                                               ) -> None:
    """trained_weight = 1 absorbs every row of the recordings into the trained statistics
    and forgets nothing: the online posterior of all the rows, which test_adapt.py shows is
    the batch FITC posterior of the old and new rows (at the trained prior mean)."""
    old = read_series([str(floors["tile"])])
    new = read_series([str(floors["carpet"])])
    model = train(old, SMALL)
    opts = OfflineAdaptOptions(trained_weight=1.0, holdout=0.0, calibrate=False,
                               max_distance=None)
    adapted = adapt_model(model, new, opts)
    fc = model.feature_config
    Xq, _ = design(new, 0, fc)
    for c, (trained, got) in enumerate(zip(model.channels, adapted.channels, strict=True)):
        assert isinstance(trained, SparseGP)
        X0, _ = design(old, c, fc)
        X1, y1 = design(new, c, fc)
        assert model.meta["training"]["channels"][("v", "omega")[c]]["rows"] == X0.shape[0]
        ref = copy.deepcopy(trained)
        OnlinePosterior.from_sparse_gp(ref, AdaptConfig(max_distance=None)).absorb_rows(X1, y1)
        for a, b in zip(got.predict(Xq), ref.predict(Xq), strict=True):
            assert np.array_equal(a, b)
        st = adapted.meta["adaptation"]["channels"][("v", "omega")[c]]
        assert st["absorbed"] == st["rows"] == X1.shape[0] and not st["refused"]
        assert st["effective_size"] == X0.shape[0] + X1.shape[0]
        # the file's number of data says what the posterior holds now
        assert got.get_state()["num_data"] == X0.shape[0] + X1.shape[0]
    assert adapted.calibration == model.calibration  # kept as trained
    assert adapted.meta["adaptation"]["calibration"] == "kept as trained"


def _lost_from(new: Series, t_lost: float, seed: int, config: ResampleConfig) -> Series:
    """``new`` with the VO reporting tracking loss from ``t_lost`` on, its readings there
    replaced by random (in range) garbage."""
    raw = new.raw
    lost = raw.vel_t >= t_lost
    vel = raw.vel.copy()
    vel[lost] = np.random.default_rng(seed).uniform(-0.5, 0.5, size=(int(lost.sum()), 2))
    bad = dataclasses.replace(raw, vel=vel, vel_ok=raw.vel_ok & ~lost)
    return Series(new.name, resample(bad, config), bad)


def test_invalid_steps_never_teach_the_model(floors: dict[str, Path]) -> None:
    model = train(read_series([str(floors["tile"])]), SMALL)
    new = read_series([str(floors["carpet"])], resample_config=model.resample_config)[0]
    rc = model.resample_config
    t_mid = float(np.median(new.raw.vel_t))
    opts = OfflineAdaptOptions(holdout=0.0, calibrate=False)
    # two recordings that differ only in what the VO read while it reported tracking loss
    a = adapt_model(model, [_lost_from(new, t_mid, 1, rc)], opts)
    b = adapt_model(model, [_lost_from(new, t_mid, 2, rc)], opts)
    X, _ = design([new], 0, model.feature_config)
    for ca, cb in zip(a.channels, b.channels, strict=True):
        assert np.array_equal(ca.predict(X)[0], cb.predict(X)[0])
        assert np.array_equal(ca.predict(X)[1], cb.predict(X)[1])
    half = a.meta["adaptation"]["channels"]["v"]["absorbed"]
    whole = adapt_model(model, [new], opts).meta["adaptation"]["channels"]["v"]["absorbed"]
    assert 0.3 * whole < half < 0.6 * whole
    # a recording whose VO never tracked teaches nothing, and says so
    with pytest.raises(AdaptingError, match="no usable row"):
        adapt_model(model, [_lost_from(new, -np.inf, 3, rc)], opts)


def test_asgp_adapt_learns_under_the_held_chair_rule_from_a_model_without_it(
        floors: dict[str, Path], tile_model: Path, tmp_path: Path,
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A model file from before the held-chair rule (``held_after_s`` off): `asgp adapt`
    reads its recordings under the rule, as the online predictor learns; the model it
    writes still predicts as trained, without it."""
    import asgp_ros.cli.adapt as cli_adapt

    model = load_model(tile_model)
    old = dataclasses.replace(model, resample_config=dataclasses.replace(
        model.resample_config, held_after_s=float("inf")))
    old_path = tmp_path / "old.npz"
    save_model(old_path, old)
    seen: list[ResampleConfig] = []
    real = cli_adapt.read_series_or_fail

    def spy(bags, args, *, resample_config):  # type: ignore[no-untyped-def]
        seen.append(resample_config)
        return real(bags, args, resample_config=resample_config)

    monkeypatch.setattr(cli_adapt, "read_series_or_fail", spy)
    out = tmp_path / "adapted.npz"
    assert main(["adapt", str(old_path), str(floors["carpet"]), "--out", str(out)]) == 0
    assert seen and seen[0].held_after_s == ResampleConfig().held_after_s
    assert dataclasses.replace(seen[0], held_after_s=float("inf")) == old.resample_config
    assert load_model(out).resample_config.held_after_s == float("inf")


def test_options_are_checked() -> None:
    for bad in (dict(trained_weight=1.5), dict(trained_weight=float("nan")),
                dict(holdout=0.9), dict(holdout=0.0, calibrate=True),
                dict(max_distance=0.0), dict(horizons_s=())):
        with pytest.raises(AdaptingError):
            OfflineAdaptOptions(**bad).validate()  # type: ignore[arg-type]


def test_asgp_adapt_writes_a_model_the_predictor_can_adapt_further(
        floors: dict[str, Path], tile_model: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "carpet.npz"
    before = _digest(tile_model)
    assert main(["adapt", str(tile_model), str(floors["carpet"]), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "held-out success" in printed and f"wrote {out}" in printed
    assert _digest(tile_model) == before
    model = load_model(out)
    assert model.meta["adaptation"]["data"]["bags"] == [str(floors["carpet"])]
    # asgp info tells what was done
    assert main(["info", str(out)]) == 0
    info = capsys.readouterr().out
    assert "adapted to 1 bag(s)" in info and "rows absorbed" in info
    # the saved posterior can adapt online again (its LA factor is in the file)
    for ch in model.channels:
        assert isinstance(ch, SparseGP)
        online = OnlinePosterior.from_sparse_gp(ch, bind=False)
        assert online.stats.rows_absorbed == 0
    # deterministic: the same inputs give the same file contents
    again = tmp_path / "again.npz"
    assert main(["adapt", str(tile_model), str(floors["carpet"]), "--out", str(again)]) == 0
    a, b = _arrays(out), _arrays(again)
    assert a.keys() == b.keys()
    for key in a:
        if key != "__meta__":
            assert np.array_equal(a[key], b[key]), key


def test_asgp_adapt_refuses_what_it_cannot_do_and_writes_nothing(
        floors: dict[str, Path], tile_model: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    carpet = str(floors["carpet"])
    before = _digest(tile_model)
    # the output pointed at the model itself, with or without --force
    for extra in ([], ["--force"]):
        assert main(["adapt", str(tile_model), carpet, "--out", str(tile_model), *extra]) != 0
        assert "refusing to overwrite" in capsys.readouterr().err
    assert _digest(tile_model) == before
    # an existing output is kept unless --force
    out = tmp_path / "out.npz"
    out.write_bytes(b"mine")
    assert main(["adapt", str(tile_model), carpet, "--out", str(out)]) != 0
    assert out.read_bytes() == b"mine"
    capsys.readouterr()
    # not an ASGP
    mlp = tmp_path / "fol.npz"
    assert main(["train", "--model", "first_order_lag", str(floors["tile"]), "--out",
                 str(mlp)]) == 0
    capsys.readouterr()
    new = tmp_path / "new.npz"
    assert main(["adapt", str(mlp), carpet, "--out", str(new)]) == 2
    err = capsys.readouterr().err
    assert "only an ASGP can be adapted" in err and len(err.strip().splitlines()) == 1
    # a model file that is not one, a bag that is not one
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"\x00" * 100)
    assert main(["adapt", str(junk), carpet, "--out", str(new)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert main(["adapt", str(tile_model), str(junk), "--out", str(new)]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    # a symbolic link loop as a bag (found by benchmarks/fuzz.py, seed 5151: a traceback)
    loop = tmp_path / "loop"
    loop.symlink_to(loop)
    assert main(["adapt", str(tile_model), str(loop), "--out", str(new)]) == 2
    err = capsys.readouterr().err
    assert "loop" in err and len(err.strip().splitlines()) == 1
    # a weight outside [0, 1] is a usage error
    assert main(["adapt", str(tile_model), carpet, "--out", str(new),
                 "--trained-weight", "nan"]) == 2
    assert not new.exists()


def test_a_short_recording_keeps_the_trained_calibration(
        floors: dict[str, Path], tile_model: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    """Half a minute gives a few dozen held-out cases: a map fitted on them is noise (a v
    scale of 1e-5 was seen), so the trained calibration is kept, and the output says why."""
    short = tmp_path / "short"
    assert main(["simulate", "--surface", "carpet", "--minutes", "0.5", "--seed", "6",
                 "--out", str(short), "--no-truth"]) == 0
    out = tmp_path / "short.npz"
    assert main(["adapt", str(tile_model), str(short), "--out", str(out)]) == 0
    assert "fewer than the 300 a calibration needs" in capsys.readouterr().out
    model, trained = load_model(out), load_model(tile_model)
    assert model.calibration == trained.calibration
    assert model.meta["adaptation"]["calibration"] == "kept as trained"
    # a recording the model was trained on: said, since its rows are in the posterior
    trained = tmp_path / "trained.npz"
    assert main(["train", "--lags", "2", "--coupled", "--inducing-v", "20", "--inducing-w",
                 "20", "--max-iter", "20", "--no-calibration", str(short), "--out",
                 str(trained)]) == 0
    capsys.readouterr()
    assert main(["adapt", str(trained), str(short), "--out", str(tmp_path / "t2.npz"),
                 "--trained-weight", "1"]) == 0
    assert "is one of the recordings" in capsys.readouterr().out
    # adapted again to a recording it was adapted to: said too (its rows counted twice,
    # silently), and the earlier adaptation's record is kept, not overwritten
    twice = tmp_path / "twice.npz"
    assert main(["adapt", str(out), str(short), "--out", str(twice)]) == 0
    printed = capsys.readouterr().out
    assert "was adapted to: its rows are in the posterior already and count twice" in printed
    record = load_model(twice).meta["adaptation"]
    assert [r["data"]["bags"] for r in record["earlier"]] == [[str(short)]]
    assert main(["info", str(twice)]) == 0
    assert f"before that (1 of 1): adapted to {short}" in capsys.readouterr().out
    # the same recording twice would count its rows twice
    again = tmp_path / "again.npz"
    assert main(["adapt", str(tile_model), str(short), str(tmp_path / "." / "short"),
                 "--out", str(again)]) == 2
    assert "the same recording" in capsys.readouterr().err and not again.exists()


def test_a_recording_trained_on_is_told_from_anywhere_and_in_a_copy(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The model file kept the bags' paths as typed: trained on `short` from one directory,
    the same bag adapted to from another (its absolute path), or a copy of it, was not told,
    and with --trained-weight 1 its rows were absorbed a second time in silence. The file
    keeps each bag's real path and content now."""
    import shutil

    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    assert main(["simulate", "--surface", "carpet", "--minutes", "0.5", "--seed", "6",
                 "--out", "short", "--no-truth"]) == 0
    assert main(["train", "--lags", "2", "--coupled", "--inducing-v", "20", "--inducing-w",
                 "20", "--max-iter", "20", "--no-calibration", "short", "--out",
                 "trained.npz"]) == 0
    shutil.copytree(work / "short", tmp_path / "copy")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    capsys.readouterr()
    for i, bag in enumerate((work / "short", tmp_path / "copy", Path("../work/short"))):
        assert main(["adapt", str(work / "trained.npz"), str(bag), "--out", f"a{i}.npz",
                     "--trained-weight", "1", "--no-calibration"]) == 0
        assert f"warning: {bag} is one of the recordings" in capsys.readouterr().out
    # another recording is not one of them, nor is one saved where the trained one was
    # (recorded again with --force: it matched on its path alone)
    assert main(["simulate", "--surface", "carpet", "--minutes", "0.5", "--seed", "7",
                 "--out", "other", "--no-truth"]) == 0
    assert main(["simulate", "--surface", "carpet", "--minutes", "0.5", "--seed", "8",
                 "--out", str(work / "short"), "--no-truth", "--force"]) == 0
    for i, bag in enumerate(("other", str(work / "short"))):
        capsys.readouterr()
        assert main(["adapt", str(work / "trained.npz"), bag, "--out", f"b{i}.npz",
                     "--no-calibration"]) == 0
        assert "one of the recordings" not in capsys.readouterr().out


def test_blocks_and_refusals(floors: dict[str, Path], monkeypatch: pytest.MonkeyPatch) -> None:
    """Rows are absorbed in blocks of bounded size, with the same posterior as one block;
    when every row is refused (here all beyond a tiny max_distance), nothing is written as
    if adapted: the error names the reason."""
    from asgp_ros.learning import adapting

    model = train(read_series([str(floors["tile"])]), SMALL)
    new = read_series([str(floors["carpet"])])
    opts = OfflineAdaptOptions(holdout=0.0, calibrate=False)
    whole = adapt_model(model, new, opts)
    monkeypatch.setattr(adapting, "BLOCK_ROWS", 97)
    blocks = adapt_model(model, new, opts)
    X, _ = design(new, 0, model.feature_config)
    for a, b in zip(whole.channels, blocks.channels, strict=True):
        for pa, pb in zip(a.predict(X), b.predict(X), strict=True):
            np.testing.assert_allclose(pb, pa, rtol=1e-9, atol=1e-12)
    assert blocks.meta["adaptation"]["channels"]["v"]["absorbed"] == X.shape[0]
    with pytest.raises(AdaptingError, match=r"no row could be absorbed.*outside"):
        adapt_model(model, new, OfflineAdaptOptions(holdout=0.0, calibrate=False,
                                                    max_distance=1e-6))


def test_a_calibration_that_training_would_not_apply_is_said_as_it_is(
        floors: dict[str, Path], tile_model: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """When the map fitted on the held-out part moves its coverage away from 95 %
    (cross-validated), the adapted model has no calibration, as training decides; its meta
    said 'kept as trained' for it."""
    from asgp_ros.core.calibration import VarianceCalibration
    from asgp_ros.learning import adapting

    def not_applied(*_args, **_kwargs):  # type: ignore[no-untyped-def]
        return VarianceCalibration(), {"fitted": True, "applied": False, "cases": 500,
                                       "cross_validated": True, "reason": "not applied: ..."}

    monkeypatch.setattr(adapting, "_calibrate_step", not_applied)
    model = dataclasses.replace(load_model(tile_model),
                                calibration=VarianceCalibration(scale=(2.0, 3.0)))
    adapted = adapt_model(model, read_series([str(floors["carpet"])]))
    assert adapted.calibration.is_identity
    assert adapted.meta["adaptation"]["calibration"].startswith("none")


def _with_meta(src: Path, dest: Path, change) -> Path:  # type: ignore[no-untyped-def]
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["__meta__"][()]))
    change(meta["meta"])
    arrays["__meta__"] = np.array(json.dumps(meta))
    np.savez(dest, **arrays)
    return dest


@pytest.mark.parametrize("record", [
    {"training_data": [1, 2]},
    {"training_data": {"bags": "abc", "duration_s": "x"}},
    {"adaptation": {"data": [1], "channels": [1], "held_out": 3}},
    {"adaptation": {"data": {"bags": 5}, "channels": {"v": {"effective_size": "x"}},
                    "held_out": {"trained": {"1.0": 3}, "adapted": {"1.0": {}}}}},
    {"training": ["x"], "selection": {"candidates": 7}, "calibration": {"fitted": 1}},
    # earlier adaptations' records, carried into the new one and shown after it was saved
    {"adaptation": {"earlier": [5, {"data": {"bags": 5}}, {"data": [1]}, {}],
                    "data": {"bags": [1, "x"], "duration_s": True}}},
    {"adaptation": {"earlier": "x", "data": {"bags": 5}}},
])
def test_a_model_file_with_a_record_of_another_shape(
        floors: dict[str, Path], tile_model: Path, tmp_path: Path, record: dict,
        capsys: pytest.CaptureFixture[str]) -> None:
    """The metadata record of a model file is free JSON: a section of another shape made
    asgp info and asgp adapt fail with a traceback. Now info says which section it cannot
    read and shows the rest; adapt does not need the record."""
    bad = _with_meta(tile_model, tmp_path / "odd.npz", lambda m: m.update(record))
    assert main(["info", str(bad)]) == 0
    out = capsys.readouterr().out
    assert "variance calibration" in out
    assert main(["adapt", str(bad), str(floors["carpet"]), "--out", str(tmp_path / "o.npz")]) == 0
    capsys.readouterr()


def test_the_commands_fail_in_one_line(floors: dict[str, Path], tile_model: Path,
                                       tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    """From an attack on the model-file commands: each of these was a traceback."""
    import warnings

    import asgp_ros.cli.adapt as adapt_cli
    import asgp_ros.cli.info as info_cli
    import asgp_ros.learning.evaluation as evaluation
    from asgp_ros.core.modelfile import ModelFileError

    def one_line_error() -> str:
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1, err
        return err

    test = str(floors["carpet_test"])
    # a horizon longer than the online predictor predicts (200 steps), with --adapt
    assert main(["evaluate", str(tile_model), test, "--adapt", "--horizons", "100"]) == 2
    assert "longer than the online predictor predicts" in one_line_error()
    # a long horizon within it: adaptation's history (which grows with it) is buffered
    # (from 7 s the replay's default 10 s buffer was refused with a traceback)
    assert main(["evaluate", str(tile_model), test, "--adapt", "--horizons", "7.4"]) == 0
    capsys.readouterr()
    # a model that diverges on the test data
    def diverging(*args: object, **kwargs: object) -> None:
        raise ValueError("channel v predicted NaN or inf")
    with monkeypatch.context() as m:
        m.setattr(evaluation, "rollout", diverging)
        assert main(["evaluate", str(tile_model), test]) == 2
        assert "rollout over" in one_line_error()
    # an adapted model the saver refuses: not written, one line
    def refuse(path: object, model: object) -> None:
        raise ModelFileError(str(path), "array 'omega.alpha' has a value beyond +-1e+15")
    with monkeypatch.context() as m:
        m.setattr(adapt_cli, "save_model", refuse)
        out = tmp_path / "adapted.npz"
        assert main(["adapt", str(tile_model), str(floors["carpet"]), "--out", str(out)]) == 2
        assert "the adapted model is not saved" in one_line_error()
        assert not out.exists()
    # a library's warning is a log record on stdout: stderr holds nothing
    real = info_cli.run
    def warns(args: object) -> int:
        warnings.warn("SparseGP: 1 negative latent variance(s) clipped", RuntimeWarning,
                      stacklevel=1)
        return real(args)
    with monkeypatch.context() as m:
        m.setattr(info_cli, "run", warns)
        assert main(["info", str(tile_model)]) == 0
        assert capsys.readouterr().err == ""


def test_long_horizons_are_rolled_out_in_small_batches(floors: dict[str, Path],
                                                      tile_model: Path,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """The linear rollout's memory grows as cases x k^2: 2,000 cases of 40 s in one batch
    took 11 GB (100 s: killed). Each batch now holds at most CHUNK_CASE_STEPS2 / k^2."""
    import asgp_ros.learning.evaluation as evaluation
    from asgp_ros.core.rollout import rollout as real

    sizes: list[int] = []

    def recorded(model: object, joy_past: np.ndarray, *args: object, **kw: object) -> object:
        sizes.append(int(np.asarray(joy_past).shape[0]))
        return real(model, joy_past, *args, **kw)  # type: ignore[arg-type]
    monkeypatch.setattr(evaluation, "rollout", recorded)
    model = load_model(tile_model)
    res = read_series([str(floors["carpet_test"])])[0].res
    idx = np.flatnonzero(res.valid)[10:1010]
    k = 200
    pose, _, _ = evaluation.rollout_cases(model, res, idx[idx + k < res.t.size], k,
                                          uncertainty="linear")
    assert max(sizes) <= evaluation.CHUNK_CASE_STEPS2 // k**2 and sum(sizes) == pose.shape[0]


def test_monte_carlo_rollouts_are_batched_by_trajectories(floors: dict[str, Path],
                                                          tile_model: Path,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    """`asgp evaluate --uncertainty mc` rolled out 4,096 cases of 1,000 trajectories at
    once: 1.9-5 GB for a few minutes of test drive, about 20 GB for one 20-minute bag with
    an automatic model. A batch now holds at most CHUNK_MC_TRAJECTORIES trajectories."""
    import asgp_ros.learning.evaluation as evaluation

    sizes: list[tuple[int, object]] = []

    def recorded(model: object, joy_past: np.ndarray, vel_past: np.ndarray,
                 joy_future: np.ndarray, **kw: object) -> object:
        sizes.append((int(np.asarray(joy_past).shape[0]), kw.get("n_samples")))
        k = joy_future.shape[1]
        B = joy_past.shape[0]
        from types import SimpleNamespace
        return SimpleNamespace(pose=np.zeros((B, k, 3)), vel=np.zeros((B, k, 2)),
                               pos_cov=np.zeros((B, k, 2, 2)))
    monkeypatch.setattr(evaluation, "rollout", recorded)
    model = load_model(tile_model)
    res = read_series([str(floors["carpet_test"])])[0].res
    idx = np.flatnonzero(res.valid)[10:1010]
    idx = idx[idx + 10 < res.t.size]
    pose, _, _ = evaluation.rollout_cases(model, res, idx, 10, uncertainty="mc")
    batch = evaluation.CHUNK_MC_TRAJECTORIES // evaluation.MC_SAMPLES
    assert all(n == evaluation.MC_SAMPLES for _, n in sizes)
    assert max(b for b, _ in sizes) <= batch and sum(b for b, _ in sizes) == pose.shape[0]
    assert len(sizes) > 1


def test_the_timeline_records_the_scale_each_prediction_used(
        floors: dict[str, Path], tile_model: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """evaluate --adapt's timeline read the variance scale after the learning that follows
    each prediction: 100 of 558 cases recorded another scale than their prediction's, up
    to 22 % off."""
    from asgp_ros.core import online
    from asgp_ros.core.adaptive import AdaptSettings
    from asgp_ros.learning import evaluation

    model = load_model(tile_model)
    (series,) = read_series([str(floors["carpet_test"])])
    used: dict[int, float] = {}
    real = online.Predictor.predict

    def predict(self: online.Predictor, now: float, joy_future: object = None, *,
                learn: bool = True) -> object:
        # the scales in force as it predicts: the published calibration's over the trained
        # one's, per speed regime (learning, after it, may change them)
        scales = [a / b for a, b in zip(self.model.calibration.speed_factors,
                                        model.calibration.speed_factors, strict=True)]
        p = real(self, now, joy_future, learn=learn)  # type: ignore[arg-type]
        if p.ok:
            used[int(p.step)] = scales[int(model.calibration.regime(p.vel_past[-1, 0]))]
        return p
    monkeypatch.setattr(online.Predictor, "predict", predict)
    replay = evaluation._replay_series(
        model, TestSeries(series.name, series.res, series.raw), 10, model.lags,
        AdaptSettings(), online.PredictorConfig(horizon_steps=10, buffer_s=20.0))
    k0 = int(series.res.k[0])
    want = np.array([used[k0 + i - 1] for i in replay["idx"]])
    assert want.size > 100 and np.ptp(want) > 0.0  # the scale moved while it drove
    np.testing.assert_allclose(replay["scale"], want, rtol=1e-9)


def test_a_model_at_another_rate_is_adapted_and_scored_where_it_is(
        floors: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """At 1 Hz the horizons 1.0 and 1.4 s are one step, scored once: asgp adapt paired the
    asked horizons with the scores and failed ('zip() argument 2 is shorter'), and at
    other rates labelled each score with the horizon asked, not the one scored."""
    model = tmp_path / "slow.npz"
    assert main(["train", "--lags", "2", "--coupled", "--inducing-v", "10", "--inducing-w",
                 "10", "--max-iter", "10", "--no-calibration", "--rate", "1",
                 str(floors["tile"]), "--out", str(model)]) == 0
    out = tmp_path / "adapted.npz"
    capsys.readouterr()
    assert main(["adapt", str(model), str(floors["carpet"]), "--out", str(out)]) == 0
    held = load_model(out).meta["adaptation"]["held_out"]
    for scores in held.values():
        if scores:
            assert set(scores) <= {"1.0", "2.0"}, scores  # 1.4 s is scored as 1.0 s
