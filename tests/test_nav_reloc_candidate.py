"""A relocalization jump is confirmed only by scans that find it where the body's motion took it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.nav.reloc_candidate import RelocCandidate, carried, found_again

GATE_M, GATE_RAD = 0.3, math.radians(5.0)
EAST = math.pi / 2  # yaw facing east: forward is +y (east), right is -x (south)


def find(c: RelocCandidate | None, x: float, y: float, moved: tuple[float, float] = (0.0, 0.0),
         yaw: float = EAST, yaw_delta: float = 0.0) -> RelocCandidate:
    return found_again(c, np.array([x, y]), yaw, 4, 0, False, moved, yaw_delta, GATE_M, GATE_RAD)


def test_scans_finding_the_jump_where_the_motion_took_it_count_up() -> None:
    """Facing east and moving 1 m forward per scan (faster than the gate), each finding 1 m further
    east is the same candidate: frames 1, 2, 3."""
    c = find(None, 5.0, 2.0)
    c = find(c, 5.0, 3.0, moved=(1.0, 0.0))
    c = find(c, 5.0, 4.0, moved=(1.0, 0.0))
    assert c.frames == 3 and (c.x, c.y) == (5.0, 4.0)


def test_a_finding_off_the_moved_candidate_starts_over() -> None:
    """A pose 0.5 m from where the motion took the candidate, or turned 10 deg from where the gyro
    took it, is another candidate: the count restarts at 1."""
    c = find(find(None, 5.0, 2.0), 5.0, 3.0, moved=(1.0, 0.0))
    assert find(c, 5.5, 3.0).frames == 1
    assert find(c, 5.0, 3.0, yaw=EAST + math.radians(10.0)).frames == 1
    assert find(c, 5.0, 3.0, yaw=EAST + math.radians(10.0), yaw_delta=math.radians(10.0)).frames == 3


def test_a_candidate_no_scan_can_test_is_carried_by_the_motion_then_dropped() -> None:
    """Scans that neither find nor contradict it move the candidate with the body (facing east,
    0.5 m to the right is 0.5 m south) and keep its count; after ``needed`` of them in a row it is
    dropped."""
    c = find(None, 5.0, 2.0)
    for k in range(1, 4):
        c = carried(c, (0.0, 0.5), 0.0, needed=3)
        assert c is not None and c.frames == 1 and c.idle == k
        assert (c.x, c.y) == pytest.approx((5.0 - 0.5 * k, 2.0))
    assert carried(c, (0.0, 0.5), 0.0, needed=3) is None
    assert carried(None, (0.0, 0.0), 0.0, needed=3) is None


def test_a_candidate_found_by_walls_is_carried_with_its_wall_count() -> None:
    """Carried, the candidate is still the one the walls found (telemetry's ``walls``, its description)."""
    c = found_again(None, np.array([5.0, 2.0]), EAST, 0, 3, True, (0.0, 0.0), 0.0, GATE_M, GATE_RAD)
    moved = carried(c, (0.0, 0.5), 0.0, needed=3)
    assert moved is not None and (moved.walls, moved.matched, moved.local) == (3, 0, True)
    assert "3 walls" in moved.describe(3)
