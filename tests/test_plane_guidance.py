"""The simulated ArduPlane's loiter guidance (sitl/plane_guidance.py: AP_L1_Control::update_loiter)
flown by a point mass whose bank follows its demand first order: the aircraft captures its
circle from far away and from its centre and holds it, without the bank reversals of the orbit vector
field it replaced (3-4 in 15 s arriving at a target)."""

from __future__ import annotations

import math

from companion.frames import GRAVITY_MPS2
from sitl.plane_guidance import L1Loiter, PlaneLimits, bank_for_accel

DT = 0.02  # s
SPEED = 17.0  # m/s, still air
BANK_TAU_S = 0.25  # the attitude loop's time constant (attitude_rates: 4 /s)


def fly(start: tuple[float, float], heading_rad: float, centre: tuple[float, float],
        seconds: float, direction: int = 1) -> tuple[list[float], list[float]]:
    """(distances to ``centre`` m, banks rad) every step of a loiter flown from ``start`` (NED m),
    clockwise (``direction`` 1) or counter-clockwise (-1)."""
    limits = PlaneLimits()
    loiter = L1Loiter(limits)
    north, east, heading, bank = start[0], start[1], heading_rad, 0.0
    distances, banks = [], []
    for _ in range(int(seconds / DT)):
        vn, ve = SPEED * math.cos(heading), SPEED * math.sin(heading)
        accel = loiter.lateral_accel(north, east, vn, ve, heading, centre, limits.loiter_radius_m, direction)
        bank += (bank_for_accel(accel, 0.0, limits.roll_limit_rad) - bank) * DT / BANK_TAU_S
        heading += GRAVITY_MPS2 * math.tan(bank) / SPEED * DT
        north, east = north + vn * DT, east + ve * DT
        distances.append(math.hypot(north - centre[0], east - centre[1]))
        banks.append(bank)
    return distances, banks


def reversals(banks: list[float], beyond_rad: float = math.radians(20.0)) -> int:
    """Sign changes between banks steeper than ``beyond_rad``."""
    signs = [math.copysign(1.0, b) for b in banks if abs(b) > beyond_rad]
    return sum(a != b for a, b in zip(signs, signs[1:]))


def test_an_aircraft_far_away_flies_to_its_loiter_circle_and_holds_it_clockwise() -> None:
    radius = PlaneLimits().loiter_radius_m
    distances, banks = fly((0.0, 0.0), 0.0, (600.0, 300.0), 90.0)
    tail = distances[-int(30.0 / DT):]
    assert all(abs(d - radius) < 3.0 for d in tail), (min(tail), max(tail))
    assert min(banks[-int(30.0 / DT):]) > 0.0  # clockwise: right bank all round
    # Head-on to the centre, joining a clockwise circle takes one veer left onto its tangent first.
    assert reversals(banks) <= 1


def test_a_counter_clockwise_loiter_holds_its_circle_banking_left() -> None:
    radius = PlaneLimits().loiter_radius_m
    distances, banks = fly((0.0, 0.0), 0.0, (600.0, 300.0), 90.0, direction=-1)
    assert all(abs(d - radius) < 3.0 for d in distances[-int(30.0 / DT):])
    assert max(banks[-int(30.0 / DT):]) < 0.0  # counter-clockwise: left bank all round
    assert reversals(banks) <= 1


def test_an_aircraft_at_the_centre_spirals_out_onto_its_circle_without_reversing_its_bank() -> None:
    radius = PlaneLimits().loiter_radius_m
    distances, banks = fly((0.0, 0.0), 0.0, (0.0, 0.0), 60.0)
    assert all(abs(d - radius) < 3.0 for d in distances[-int(20.0 / DT):])
    assert reversals(banks) == 0
