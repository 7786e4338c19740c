"""Unit tests of sitl.jitter.JitterCorrection (times in seconds)."""

from __future__ import annotations

import pytest

from companion.jitter import JitterCorrection

CLOCK_OFFSET_S = 1000.0  # remote clock reads local + 1000 s


def test_first_sample_is_placed_at_its_arrival() -> None:
    jc = JitterCorrection()
    assert jc.offset_s is None
    assert jc.correct(remote_s=1001.0, local_s=1.02) == pytest.approx(1.02)
    assert jc.offset_s == pytest.approx(1.02 - 1001.0)


def test_offset_converges_to_the_fastest_transport() -> None:
    jc = JitterCorrection()
    lags = [0.030, 0.012, 0.002, 0.025, 0.018]
    for i, lag in enumerate(lags):
        capture = 0.1 * i
        jc.correct(capture + CLOCK_OFFSET_S, capture + lag)
    # A later sample is mapped with the minimum lag (2 ms) assumed as zero.
    mapped = jc.correct(1.0 + CLOCK_OFFSET_S, 1.0 + 0.020)
    assert mapped == pytest.approx(1.0 + 0.002)


def test_sample_faster_than_seen_lowers_the_offset_and_is_kept() -> None:
    jc = JitterCorrection()
    jc.correct(0.0 + CLOCK_OFFSET_S, 0.050)
    assert jc.correct(0.1 + CLOCK_OFFSET_S, 0.101) == pytest.approx(0.101)
    assert jc.offset_s == pytest.approx(0.001 - CLOCK_OFFSET_S)


def test_sample_older_than_max_lag_is_dropped_and_counted() -> None:
    jc = JitterCorrection(max_lag_s=0.5)
    jc.correct(0.0 + CLOCK_OFFSET_S, 0.001)
    assert jc.correct(1.0 + CLOCK_OFFSET_S, 1.0 + 0.6) is None
    assert jc.rejected == 1
    assert jc.correct(2.0 + CLOCK_OFFSET_S, 2.0 + 0.4) == pytest.approx(2.001)


def test_sample_claiming_to_be_from_the_future_is_dropped_and_counted() -> None:
    jc = JitterCorrection(max_lag_s=0.5)
    jc.correct(0.0 + CLOCK_OFFSET_S, 0.001)
    # Stamped 0.7 s after its arrival under the established clock relation.
    assert jc.correct(1.7 + CLOCK_OFFSET_S, 1.0) is None
    assert jc.rejected == 1
    # The offset is untouched, so normal samples keep their mapping.
    assert jc.correct(2.0 + CLOCK_OFFSET_S, 2.003) == pytest.approx(2.001)


def test_remote_clock_jumping_forward_is_relearned_after_a_run() -> None:
    jc = JitterCorrection(max_lag_s=0.5, rebase_after=3)
    jc.correct(0.0 + CLOCK_OFFSET_S, 0.001)
    jump = 10.0
    results = [jc.correct(t + CLOCK_OFFSET_S + jump, t + 0.001) for t in (1.0, 1.1, 1.2, 1.3)]
    assert results[:2] == [None, None]
    assert results[2] == pytest.approx(1.201)
    assert results[3] == pytest.approx(1.301)
    assert jc.rejected == 2


def test_remote_clock_jumping_back_is_relearned_as_the_window_slides() -> None:
    jc = JitterCorrection(max_lag_s=0.5, window=4)
    jc.correct(0.0 + CLOCK_OFFSET_S, 0.001)
    back = 5.0
    results = [jc.correct(t + CLOCK_OFFSET_S - back, t + 0.001) for t in (1, 2, 3, 4, 5)]
    assert results[:3] == [None, None, None]
    assert results[3] == pytest.approx(4.001)
    assert results[4] == pytest.approx(5.001)


def test_same_clock_lockstep_maps_identity() -> None:
    jc = JitterCorrection()
    for k in range(3, 50):  # the first sample arrives with zero lag
        t = 0.005 * k
        assert jc.correct(t - 0.005 * (k % 3), t) == pytest.approx(t - 0.005 * (k % 3))


def test_invalid_parameters_are_refused() -> None:
    with pytest.raises(ValueError):
        JitterCorrection(max_lag_s=0.0)
    with pytest.raises(ValueError):
        JitterCorrection(window=0)
