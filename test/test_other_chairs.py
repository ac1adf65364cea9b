"""benchmarks/other_chairs.py: the chairs it draws are valid and within the documented
ranges, and it never writes into a directory that exists."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest


@pytest.fixture(scope="module")
def bench(load_benchmark):
    return load_benchmark("other_chairs")


def test_drawn_chairs_are_valid_and_within_the_documented_ranges(bench):
    rng = np.random.default_rng(3)
    for surface in ("tile", "carpet"):
        for _ in range(20):
            chair = dataclasses.asdict(bench.sample_chair(rng, surface))
            assert chair["surface"] == surface
            for name, (lo, hi) in bench.RANGES.items():
                assert lo <= chair[name] <= hi, name
            ratio = chair["wheel_speed_max"] / chair["v_max"]
            assert bench.WHEEL_SPEED_RATIO[0] <= ratio <= bench.WHEEL_SPEED_RATIO[1]


def test_an_existing_out_directory_is_refused_and_left_alone(bench, tmp_path, capsys):
    mine = tmp_path / "results" / "chair_0" / "asgp.npz"
    mine.parent.mkdir(parents=True)
    mine.write_text("the user's")
    with pytest.raises(SystemExit) as exc:
        bench.main(["--chairs", "1", "--out", str(tmp_path / "results")])
    assert exc.value.code == 2 and "exists" in capsys.readouterr().err
    assert mine.read_text() == "the user's"
    assert [p.name for p in (tmp_path / "results").rglob("*")] == ["chair_0", "asgp.npz"]
