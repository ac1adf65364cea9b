"""OverrideGate: which joy_override may still drive the chair, on a clock the test sets."""

from __future__ import annotations

import math

import pytest

from asgp_ros.serial.override_gate import MAX_AHEAD_S, OverrideGate

T = 0.15  # override_timeout


def test_an_unstamped_command_is_fresh_for_timeout_after_its_arrival():
    g = OverrideGate()
    assert g.fresh(0.0, 100.0, T) is None  # nothing yet
    assert g.offer((0.3, -0.1), None, arrival=10.0, clock_now=100.0, timeout=T)
    assert g.fresh(10.0, 100.0, T) == (0.3, -0.1)
    assert g.fresh(10.0 + T - 1e-9, 500.0, T) == (0.3, -0.1)  # the ROS clock plays no part
    assert g.fresh(10.0 + T + 1e-6, 100.0, T) is None
    assert g.age(10.5) == pytest.approx(0.5)


def test_a_stamped_command_older_than_the_timeout_on_arrival_is_refused_and_counted():
    g = OverrideGate()
    assert g.offer((0.2, 0.0), 99.95, arrival=10.0, clock_now=100.0, timeout=T)
    # held back by the transport: stamped 1 s ago, arriving now
    assert not g.offer((-0.5, 0.5), 99.1, arrival=10.05, clock_now=100.1, timeout=T)
    assert g.refused_stale == 1
    assert g.last_refused_age == pytest.approx(1.0)
    # the earlier command is kept, with its own freshness; the late one never counts
    assert g.fresh(10.05, 100.05, T) == (0.2, 0.0)
    assert g.fresh(10.11, 100.11, T) is None  # 0.16 s after the earlier stamp
    assert g.refusing(10.2)
    assert not g.refusing(11.1)  # none refused in the last second


def test_a_late_command_stops_counting_timeout_after_its_stamp():
    g = OverrideGate()
    assert g.offer((0.4, 0.0), 99.9, arrival=10.0, clock_now=100.0, timeout=T)  # 0.1 s old
    assert g.fresh(10.04, 100.04, T) == (0.4, 0.0)
    assert g.fresh(10.06, 100.06, T) is None  # fresh by arrival, not by its stamp


def test_a_stamp_ahead_of_the_clock_is_still_bounded_by_arrival():
    g = OverrideGate()
    assert g.offer((0.4, 0.0), 100.9, arrival=10.0, clock_now=100.0, timeout=T)
    assert g.fresh(10.1, 100.1, T) == (0.4, 0.0)
    assert g.fresh(10.2, 100.2, T) is None


@pytest.mark.parametrize("ahead", [MAX_AHEAD_S + 0.01, 30.0, 86400.0])
def test_a_stamp_of_another_timeline_ahead_is_refused(ahead):
    """A layer on a replayed /clock a day ahead judges data that are not the chair's: its
    overrides are refused, counted, and said to be ahead."""
    g = OverrideGate()
    assert not g.offer((0.4, 0.0), 100.0 + ahead, arrival=10.0, clock_now=100.0, timeout=T)
    assert g.fresh(10.01, 100.01, T) is None and g.refused_stale == 1
    assert g.refusing(10.5) and f"{ahead:.3f} s ahead" in g.refusal(T)
    assert not g.offer((0.4, 0.0), 99.0, arrival=11.0, clock_now=100.0, timeout=T)
    assert "1.000 s before this node's clock" in g.refusal(T)


@pytest.mark.parametrize("bad", [math.nan, -math.inf])
def test_a_stamp_or_clock_that_is_not_a_number_is_refused(bad):
    g = OverrideGate()
    assert not g.offer((0.4, 0.0), 100.0, arrival=10.0, clock_now=bad, timeout=T)
    assert not g.offer((0.4, 0.0), -bad, arrival=10.0, clock_now=100.0, timeout=T)
    assert g.fresh(10.0, 100.0, T) is None and g.refused_stale == 2


def test_refusals_stop_being_reported_once_a_command_is_accepted():
    g = OverrideGate()
    assert not g.offer((0.4, 0.0), 90.0, arrival=10.0, clock_now=100.0, timeout=T)
    assert g.refusing(10.1)
    assert g.offer((0.4, 0.0), 100.2, arrival=10.2, clock_now=100.2, timeout=T)
    assert not g.refusing(10.3)


def test_a_timeout_raised_later_does_not_bring_back_a_stale_command():
    """override_timeout raised at runtime (0.1 -> 1.0 s) 0.49 s after the last override:
    the bridge wrote that command five times more and the board applied it again. A
    command stays fresh for the shorter of the timeout now and the one it came under."""
    gate = OverrideGate()
    assert gate.offer((0.5, 0.0), 100.0, arrival=10.0, clock_now=100.0, timeout=0.1)
    assert gate.fresh(10.05, 100.05, 0.1) == (0.5, 0.0)
    assert gate.fresh(10.49, 100.49, 1.0) is None
    assert gate.fresh_until(1.0) == pytest.approx(10.1)
    # lowering it takes effect at once; a command accepted under the new one keeps it
    assert gate.offer((0.5, 0.0), 100.5, arrival=10.5, clock_now=100.5, timeout=1.0)
    assert gate.fresh(10.6, 100.6, 0.05) is None
    assert gate.fresh(11.4, 101.4, 1.0) == (0.5, 0.0)


def test_an_older_command_arriving_after_a_newer_one_is_refused():
    """A command stamped 0.1 s before the one in force, delivered after it (out of order):
    it replaced the newer decision (forward 0.9 after reverse -0.5). It is refused and
    counted while the newer one is fresh; once that one is stale, a late one counts as
    any other."""
    gate = OverrideGate()
    assert gate.offer((-0.5, 0.0), 100.0, arrival=10.0, clock_now=100.0, timeout=0.15)
    assert not gate.offer((0.9, 0.0), 99.9, arrival=10.01, clock_now=100.01, timeout=0.15)
    assert gate.refused_older == 1 and gate.fresh(10.02, 100.02, 0.15) == (-0.5, 0.0)
    # unstamped ones are judged by arrival alone, as before
    assert gate.offer((0.2, 0.0), None, arrival=10.03, clock_now=100.03, timeout=0.15)
    assert gate.offer((0.3, 0.0), 100.2, arrival=10.2, clock_now=100.2, timeout=0.15)
    assert not gate.offer((0.4, 0.0), 100.19, arrival=10.25, clock_now=100.25, timeout=0.15)
    assert gate.refused_older == 2
    # the one in force gone stale (by its arrival), a late command is taken
    assert gate.offer((0.4, 0.0), 100.3, arrival=10.5, clock_now=100.4, timeout=0.15)
    assert gate.offer((0.1, 0.0), 100.29, arrival=10.7, clock_now=100.4, timeout=0.15)
