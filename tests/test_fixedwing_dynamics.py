"""The fixed-wing truth model (sitl/fixedwing.py): coordinated turns, sideslip, stall, wind.

The airframe is flown here by the autopilot's own attitude loops (sitl/plane_guidance.py) on
the *truth* (no sensors, no estimator), so each test sees the model alone.
"""

from __future__ import annotations

import math

import numpy as np

from companion.frames import GRAVITY_MPS2, wrap_pi
from sitl.dynamics import GaussianStream, WindConfig
from sitl.fixedwing import FixedWingCommand, FixedWingDynamics, FixedWingParams, lift_drag_coefficients
from sitl.plane_guidance import attitude_rates

DT = 1.0 / 400.0
CALM = WindConfig(gust_std_mps=0.0)


class Pilot:
    """Holds a bank angle, a height and an airspeed on the truth (P loops), with optional rudder."""

    def __init__(self, dyn: FixedWingDynamics, *, bank_rad: float = 0.0, height_m: float = 100.0,
                 airspeed_mps: float = 17.0, rudder_rad_s: float = 0.0) -> None:
        self.dyn, self.bank, self.height, self.airspeed, self.rudder = dyn, bank_rad, height_m, airspeed_mps, rudder_rad_s

    def command(self) -> FixedWingCommand:
        d = self.dyn
        roll, pitch, _ = d.euler()
        climb_d = 0.3 * (self.height + d.pz)
        pitch_d = max(-0.3, min(0.3, 0.05 + 0.1 * (climb_d + d.vz)))
        p, q, r = attitude_rates(self.bank, pitch_d, roll, pitch, (d.wx, d.wy, d.wz), d.airspeed, self.rudder)
        throttle = 0.2 + 0.1 * (self.airspeed - d.airspeed) + 0.05 * (climb_d + d.vz)
        return FixedWingCommand(throttle=throttle, roll_rate=p, pitch_rate=q, yaw_rate=r)

    def fly(self, seconds: float) -> list[tuple[float, ...]]:
        """Step ``seconds``; per step (yaw rad, airspeed, beta, ground course, vn, ve, fy)."""
        out = []
        d = self.dyn
        for _ in range(round(seconds / DT)):
            d.step(DT, self.command())
            out.append((d.euler()[2], d.airspeed, d.beta, math.atan2(d.vy, d.vx), d.vx, d.vy, d.fy))
        return out


def airborne(wind: WindConfig = CALM, yaw_rad: float = 0.0, seed: int = 1) -> FixedWingDynamics:
    return FixedWingDynamics(noise=GaussianStream(seed), wind=wind, start_ned=(0.0, 0.0, -100.0),
                             start_yaw_rad=yaw_rad, start_airspeed_mps=17.0)


def mean_turn_rate(samples: list[tuple[float, ...]]) -> float:
    """Heading rate (rad/s) from the unwrapped yaw over the samples."""
    yaw = np.unwrap([s[0] for s in samples])
    return float((yaw[-1] - yaw[0]) / (DT * (len(samples) - 1)))


def test_lift_collapses_past_the_critical_angle_of_attack() -> None:
    p = FixedWingParams()
    peak, _ = lift_drag_coefficients(p.alpha_cl_max_rad, p)
    past, drag_past = lift_drag_coefficients(p.alpha_cl_max_rad + math.radians(6.0), p)
    assert math.radians(10.0) < p.alpha_cl_max_rad < p.alpha_stall_rad
    assert peak > 1.0
    assert past < 0.4 * peak
    assert drag_past > 2.0 * lift_drag_coefficients(0.0, p)[1]
    assert 9.0 < p.stall_speed_mps < 11.0


def test_a_coordinated_level_turn_has_turn_rate_g_tan_phi_over_v_and_no_sideslip() -> None:
    for bank_deg in (20.0, 30.0, 45.0):
        dyn = airborne()
        pilot = Pilot(dyn, bank_rad=math.radians(bank_deg))
        pilot.fly(15.0)  # settle into the turn
        samples = pilot.fly(10.0)
        airspeed = float(np.mean([s[1] for s in samples]))
        expected = GRAVITY_MPS2 * math.tan(math.radians(bank_deg)) / airspeed
        assert abs(mean_turn_rate(samples) - expected) < 0.02 * expected, bank_deg
        assert max(abs(s[2]) for s in samples) < math.radians(0.5), bank_deg  # sideslip
        assert max(abs(s[6]) for s in samples) < 0.1, bank_deg  # no lateral specific force: the ball centred
        assert abs(dyn.pz + 100.0) < 2.0


def test_a_rudder_offset_holds_a_steady_sideslip_the_accelerometer_feels() -> None:
    dyn = airborne()
    pilot = Pilot(dyn, rudder_rad_s=0.2)
    pilot.fly(10.0)
    samples = pilot.fly(5.0)
    betas = [s[2] for s in samples]
    assert min(abs(b) for b in betas) > math.radians(4.0)
    assert abs(float(np.mean([s[6] for s in samples]))) > 1.0  # m/s^2 of side force


def test_below_the_stall_speed_the_wing_stalls_and_the_aircraft_loses_height() -> None:
    dyn = airborne()
    stalled_at, lowest = None, -100.0
    for i in range(round(20.0 / DT)):  # engine off, nose held 20 deg up
        roll, pitch, _ = dyn.euler()
        p, q, r = attitude_rates(0.0, math.radians(20.0), roll, pitch, (dyn.wx, dyn.wy, dyn.wz), dyn.airspeed)
        dyn.step(DT, FixedWingCommand(throttle=0.0, roll_rate=p, pitch_rate=q, yaw_rate=r))
        if dyn.stalled and stalled_at is None:
            stalled_at = (dyn.airspeed, -dyn.pz, i * DT)
        lowest = max(lowest, dyn.pz)
    assert stalled_at is not None
    airspeed, height, _ = stalled_at
    assert airspeed < FixedWingParams().stall_speed_mps + 1.0
    assert -lowest < height - 15.0  # sank more than 15 m after the stall
    flying = airborne()
    Pilot(flying).fly(5.0)
    assert not flying.stalled


def test_wind_changes_the_ground_track_but_not_the_airspeed() -> None:
    calm, windy = airborne(), airborne(WindConfig(mean_ned_mps=(0.0, 5.0, 0.0), gust_std_mps=0.0))
    calm_samples = Pilot(calm).fly(20.0)[-2000:]
    windy_samples = Pilot(windy).fly(20.0)[-2000:]
    calm_air = float(np.mean([s[1] for s in calm_samples]))
    windy_air = float(np.mean([s[1] for s in windy_samples]))
    assert abs(calm_air - windy_air) < 0.1
    for yaw, airspeed, beta, course, vn, ve, _ in windy_samples[::100]:
        # ground velocity = airspeed along the heading (no sideslip) + the wind
        assert abs(vn - airspeed * math.cos(yaw)) < 0.1
        assert abs(ve - airspeed * math.sin(yaw) - 5.0) < 0.1
        assert abs(beta) < math.radians(0.5)
        assert abs(wrap_pi(course - yaw)) > math.radians(10.0)  # drift: the track is not the heading
    for yaw, _, _, course, *_ in calm_samples[::100]:
        assert abs(wrap_pi(course - yaw)) < math.radians(0.2)


def test_gusts_are_seeded() -> None:
    gusty = WindConfig(mean_ned_mps=(2.0, 0.0, 0.0), gust_std_mps=1.0)
    a, b = airborne(gusty, seed=3), airborne(gusty, seed=3)
    Pilot(a).fly(3.0)
    Pilot(b).fly(3.0)
    assert (a.px, a.py, a.pz, a.qw) == (b.px, b.py, b.pz, b.qw)
