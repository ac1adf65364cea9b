"""The shared parameter-table checks used by the bridge and VO nodes."""

from __future__ import annotations

import math

import pytest

from asgp_ros.common.paramspec import ParamSpec, check_values

SPECS = (
    ParamSpec("flag", True, "a switch"),
    ParamSpec("count", 3, "an integer", 1, 10),
    ParamSpec("rate", 5.0, "Hz", 0.5, 50.0),
    ParamSpec("topic", "joy", "a name"),
)


def test_defaults_fill_missing_values_and_ints_become_floats_where_declared():
    v = check_values(SPECS, {"rate": 10})
    assert v == {"flag": True, "count": 3, "rate": 10.0, "topic": "joy"}
    assert isinstance(v["rate"], float)


@pytest.mark.parametrize("values,match", [
    ({"flag": 1}, "flag must be a boolean"),
    ({"count": 2.0}, "count must be an integer"),
    ({"count": True}, "count must be an integer"),
    ({"count": 11}, r"count = 11 is outside \[1, 10\]"),
    ({"rate": "fast"}, "rate must be a number"),
    ({"rate": math.nan}, "rate must be finite"),
    ({"rate": 0.1}, "rate = 0.1 is outside"),
    ({"topic": 3}, "topic must be a string"),
])
def test_bad_values_name_the_parameter(values, match):
    with pytest.raises(ValueError, match=match):
        check_values(SPECS, values)
