"""The autopilot's attitude at any instant of the last second (companion/nav/attitude_history.py)."""

from __future__ import annotations

import math

import pytest

from companion.nav.attitude_history import AttitudeHistory


def test_the_attitude_between_two_samples_is_interpolated_and_yaw_the_short_way_round() -> None:
    history = AttitudeHistory()
    history.add(1.00, (0.0, 0.1, math.pi - 0.1))
    history.add(1.02, (0.2, 0.3, -math.pi + 0.1))  # yaw through +/-180 deg: 0.2 rad on, not 6.08 back
    roll, pitch, yaw = history.at(1.015)
    assert (roll, pitch) == (pytest.approx(0.15), pytest.approx(0.25))
    assert yaw == pytest.approx(-math.pi + 0.05)


def test_outside_the_samples_the_nearest_end_unless_further_than_the_gap_allowed() -> None:
    history = AttitudeHistory()
    assert history.at(1.0) is None
    history.add(1.00, (0.1, 0.0, 0.0))
    history.add(1.02, (0.2, 0.0, 0.0))
    history.add(1.50, (0.3, 0.0, 0.0))
    assert history.at(0.5) == (0.1, 0.0, 0.0) and history.at(2.0) == (0.3, 0.0, 0.0)
    assert history.at(0.95, max_gap_s=0.1) == (0.1, 0.0, 0.0) and history.at(0.85, max_gap_s=0.1) is None
    assert history.at(1.62, max_gap_s=0.1) is None
    assert history.at(1.26, max_gap_s=0.1) is None  # 0.24 s from either sample around it
    assert history.at(1.45, max_gap_s=0.1) is not None


def test_a_sample_out_of_order_is_ignored_and_samples_older_than_the_span_are_forgotten() -> None:
    history = AttitudeHistory(span_s=1.0)
    history.add(1.0, (0.1, 0.0, 0.0))
    history.add(2.0, (0.2, 0.0, 0.0))
    history.add(1.5, (9.0, 0.0, 0.0))  # older than the newest: ignored
    assert history.at(1.5)[0] == pytest.approx(0.15)
    history.add(2.5, (0.3, 0.0, 0.0))  # 1.0 s is now more than a second old
    assert history.at(0.0) == (0.2, 0.0, 0.0)
