"""Offline accuracy of the GNSS pseudo-attitude over a fixed wing's flight with truth (issue 15's
roll figure; tests/test_gnss_pseudo_attitude_eval.py runs it, ``python -m
sitl.pseudo_attitude_eval`` prints the table).

The flight: a small fixed wing at constant airspeed (default 18 m/s) in still air, flying
straight legs and coordinated turns (bank 15 to 35 deg either way) with climbs and descents (up to
2.5 m/s), for 300 s like the seed's Table 1 plan. The bank follows its demand as ArduPlane's roll
loop does, first order (``roll_tau_s``, RLL2SRV_TCONST) within a roll-rate limit
(``max_roll_rate_dps``), the roll rate reaching its demand with the airframe's roll-mode lag
(``roll_mode_tau_s``); the flight-path angle follows the climb demand first order
(``climb_tau_s``), its rate lagging by the pitch response (``pitch_tau_s``); the heading turns
as the lift, banked and normal to the air velocity, makes it (coordinated: no lateral specific
force). Integrated at ``step_s``. A steady wind (``wind_ned_mps``) changes the ground velocity the
GNSS measures but not the acceleration; the pseudo-roll, about the ground velocity, then differs
from the bank by the crab (the flow's offsets turn it to the body, true_attitude.true_euler), so the
gyro blend's truth is only the bank in still air.

The receiver: fixes at epochs ``k / rate_hz`` (s) with the true NED velocity plus white noise
of ``doppler_sigma_mps`` per axis, as sitl/gnss_sim.py (whose defaults are 5 Hz, 0.05 m/s and a
0.1 s latency); each fix arrives ``latency_s`` after its epoch, stamped at its epoch.

The estimator: :class:`~.pseudo_attitude.DopplerAccelerationFilter` of ``jerk_psd``, queried at
instants ``query_hz`` apart (the pipeline's frame instants, between fixes) either causally (lag 0:
predicted from the last fix before the instant, the pipeline's stamping before 0.6 s of smoothing
became its default) or smoothed with the fixes
up to ``lag_s`` after it (:meth:`~.pseudo_attitude.DopplerAccelerationFilter.smoothed`: the
estimate describes the instant and is ready ``lag_s`` plus the latency after it); optionally
blended with a gyro's roll rate (:class:`~.pseudo_attitude.GyroAidedAngle` of ``gyro_tau_s``; the
gyro measures the true Euler roll rate with a constant bias, a scale error and white noise, as
the autopilot's IMU would after the Euler conversion).

Truth: the exact pseudo-attitude (:func:`~.pseudo_attitude.pseudo_attitude` of the true velocity
and acceleration); in this coordinated flight in still air it is the airframe's attitude (bank,
flight path, heading; no angle of attack). Errors are in degrees, split into instants within ``transition_margin_s`` of a manoeuvre (bank or flight-path
rate above ``transition_rate_dps``) and the rest (straight legs and steady turns).
"""

from __future__ import annotations

import argparse
import itertools
import math
from dataclasses import dataclass

import numpy as np

from companion.frames import GRAVITY_MPS2, wrap_pi
from companion.nav.gnss_flow.pseudo_attitude import (DopplerAccelerationFilter, GyroAidedAngle, KinematicEstimate,
                                                     pseudo_attitude)


@dataclass(frozen=True)
class FlightPlan:
    """A seeded flight of legs; speeds m/s, angles deg, times s, NED."""

    duration_s: float = 300.0
    airspeed_mps: float = 18.0
    wind_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    roll_tau_s: float = 0.5  # bank response time constant
    max_roll_rate_dps: float = 45.0  # bank rate limit
    roll_mode_tau_s: float = 0.1  # the roll rate's lag behind its demand
    climb_tau_s: float = 1.5  # flight-path angle response time constant
    pitch_tau_s: float = 0.4  # the flight-path rate's lag behind its demand
    leg_s: tuple[float, float] = (8.0, 25.0)  # each leg's duration, drawn uniformly
    bank_deg: tuple[float, float] = (15.0, 35.0)  # a turn's bank magnitude, drawn uniformly
    max_climb_mps: float = 2.5  # climb or sink demand magnitude, at most
    start_ned_m: tuple[float, float, float] = (0.0, 0.0, -100.0)
    step_s: float = 0.005  # integration step (divides 1 / rate_hz and 1 / query_hz)
    seed: int = 0


@dataclass(frozen=True)
class Flight:
    """Truth sampled every ``plan.step_s`` from 0: time s, position NED m (from ``start_ned_m``),
    velocity and acceleration NED (m/s, m/s^2), the airframe's ZYX Euler angles (bank, flight
    path, heading) and their rates, rad and rad/s (body x along the air velocity: no angle of
    attack)."""

    t: np.ndarray  # (n,)
    position_ned: np.ndarray  # (n, 3)
    velocity_ned: np.ndarray  # (n, 3)
    acceleration_ned: np.ndarray  # (n, 3)
    euler: np.ndarray  # (n, 3)
    euler_rates: np.ndarray  # (n, 3)

    @property
    def bank(self) -> np.ndarray:
        """(n,) rad."""
        return self.euler[:, 0]

    @property
    def bank_rate(self) -> np.ndarray:
        """(n,) rad/s."""
        return self.euler_rates[:, 0]


@dataclass(frozen=True)
class Receiver:
    """The simulated receiver (sitl/gnss_sim.py defaults)."""

    rate_hz: float = 5.0
    doppler_sigma_mps: float = 0.05
    latency_s: float = 0.1
    seed: int = 1


@dataclass(frozen=True)
class Gyro:
    """The autopilot's gyro: white noise (deg/s/sqrt(Hz)), bias (deg/s: what the autopilot's boot
    calibration leaves, temperature drift), scale error (fraction), each axis alike."""

    noise_dps_rthz: float = 0.01
    bias_dps: float = 0.1
    scale_error: float = 0.005


@dataclass(frozen=True)
class Estimator:
    """The Doppler filter's jerk PSD (m^2/s^5), the smoothing lag (s, 0: causal) and the gyro
    blend's time constant (s, 0: no gyro)."""

    jerk_psd: float = 0.5
    lag_s: float = 0.0
    gyro_tau_s: float = 0.0


@dataclass(frozen=True)
class Errors:
    """(roll, pitch, yaw) errors (deg, estimate minus truth) at instants (s), with whether each
    lies in a manoeuvre (:func:`manoeuvring`)."""

    t: np.ndarray  # (m,) s
    euler_deg: np.ndarray  # (m, 3)
    transition: np.ndarray  # (m,) bool

    def std(self, mask: np.ndarray | None = None) -> np.ndarray:
        """(roll, pitch, yaw) error std, deg, over ``mask`` (all instants by default)."""
        return self.euler_deg[slice(None) if mask is None else mask].std(axis=0)

    def rms(self, mask: np.ndarray | None = None) -> np.ndarray:
        """(roll, pitch, yaw) RMS error, deg, over ``mask``."""
        return np.sqrt(np.mean(self.euler_deg[slice(None) if mask is None else mask] ** 2, axis=0))


def fly(plan: FlightPlan) -> Flight:
    """Integrate the plan's legs (module docstring)."""
    rng = np.random.default_rng(plan.seed)
    n = round(plan.duration_s / plan.step_s) + 1
    demands = np.zeros((n, 2))  # bank rad, climb m/s
    start, straight = 0, True
    while start < n:
        length = round(rng.uniform(*plan.leg_s) / plan.step_s)
        bank = 0.0 if straight else math.radians(rng.uniform(*plan.bank_deg)) * rng.choice([-1.0, 1.0])
        climb = rng.choice([0.0, 0.0, 1.0, -1.0]) * rng.uniform(0.5, 1.0) * plan.max_climb_mps
        demands[start:start + length] = bank, climb
        start, straight = start + length, not straight
    v_air, dt = plan.airspeed_mps, plan.step_s
    max_rate = math.radians(plan.max_roll_rate_dps)
    bank, bank_rate, heading, gamma, gamma_rate = 0.0, 0.0, 0.0, 0.0, 0.0
    position = np.array(plan.start_ned_m, dtype=float)
    out = np.zeros((n, 16))
    for i in range(n):
        bank_rate_demand = float(np.clip((demands[i, 0] - bank) / plan.roll_tau_s, -max_rate, max_rate))
        gamma_rate_demand = (math.asin(demands[i, 1] / v_air) - gamma) / plan.climb_tau_s
        # the lift's vertical part holds the weight and curves the path up, its horizontal part turns it
        ch, sh, cg, sg = math.cos(heading), math.sin(heading), math.cos(gamma), math.sin(gamma)
        heading_rate = (GRAVITY_MPS2 * cg + v_air * gamma_rate) * math.tan(bank) / (v_air * cg)
        velocity = v_air * np.array([cg * ch, cg * sh, -sg]) + plan.wind_ned_mps
        acceleration = v_air * np.array([-sg * gamma_rate * ch - cg * sh * heading_rate,
                                         -sg * gamma_rate * sh + cg * ch * heading_rate, -cg * gamma_rate])
        out[i] = (i * dt, *position, *velocity, *acceleration, bank, gamma, heading, bank_rate, gamma_rate,
                  heading_rate)
        position += velocity * dt
        bank += bank_rate * dt
        heading += heading_rate * dt
        gamma += gamma_rate * dt
        bank_rate += dt / plan.roll_mode_tau_s * (bank_rate_demand - bank_rate)
        gamma_rate += dt / plan.pitch_tau_s * (gamma_rate_demand - gamma_rate)
    return Flight(out[:, 0], out[:, 1:4], out[:, 4:7], out[:, 7:10], out[:, 10:13], out[:, 13:16])


def manoeuvring(flight: Flight, rate_dps: float = 2.0, margin_s: float = 1.0) -> np.ndarray:
    """(n,) bool: within ``margin_s`` (s) of a bank or flight-path rate above ``rate_dps`` (deg/s)."""
    changing = np.abs(flight.euler_rates[:, :2]).max(axis=1) > math.radians(rate_dps)
    margin = round(margin_s / float(flight.t[1] - flight.t[0]))
    return np.convolve(changing, np.ones(2 * margin + 1), mode="same") > 0


def evaluate(flight: Flight, receiver: Receiver, estimator: Estimator, gyro: Gyro = Gyro(), query_hz: float = 10.0,
             settle_s: float = 10.0, transition_rate_dps: float = 2.0,
             transition_margin_s: float = 1.0) -> Errors:
    """The estimator's pseudo-attitude errors against the truth at instants ``query_hz`` apart,
    offset half a step from the fixes' epochs, from ``settle_s`` on (module docstring); ``gyro``
    is used when the estimator blends one."""
    rng = np.random.default_rng(receiver.seed)
    step = float(flight.t[1] - flight.t[0])
    fix_every, query_every = round(1.0 / (receiver.rate_hz * step)), round(1.0 / (query_hz * step))
    filt = DopplerAccelerationFilter(jerk_psd=estimator.jerk_psd, history_s=estimator.lag_s + 1.0)
    fixes = list(range(0, len(flight.t), fix_every))
    queries = list(range(round(settle_s / step) + query_every // 2, len(flight.t), query_every))
    lag_steps = round(estimator.lag_s / step)
    near_change = manoeuvring(flight, transition_rate_dps, transition_margin_s)
    blend = GyroAidedAngle(estimator.gyro_tau_s) if estimator.gyro_tau_s > 0 else None
    gyro_rng = np.random.default_rng(receiver.seed + 1)
    errors, kept, next_fix, previous = [], [], 0, queries[0]
    for i in queries:
        while next_fix < len(fixes) and fixes[next_fix] <= i + lag_steps:
            k = fixes[next_fix]
            filt.update(flight.t[k], flight.velocity_ned[k] + rng.normal(0.0, receiver.doppler_sigma_mps, 3),
                        receiver.doppler_sigma_mps)
            next_fix += 1
        if fixes[next_fix - 1] < i + lag_steps and next_fix == len(fixes):
            break  # the flight ended before this instant's lag
        t = float(flight.t[i])
        estimate = filt.smoothed(t) if estimator.lag_s > 0 else filt.estimate(t)
        truth = KinematicEstimate(t, flight.velocity_ned[i], flight.acceleration_ned[i], np.eye(6))
        got, want = pseudo_attitude(estimate), pseudo_attitude(truth)
        assert got is not None and want is not None  # cruise: always defined
        roll = got.roll
        if blend is not None:
            span = (i - previous) * step
            increment = ((1.0 + gyro.scale_error) * float(np.sum(flight.bank_rate[previous:i])) * step
                         + math.radians(gyro.bias_dps) * span
                         + math.radians(gyro.noise_dps_rthz) * math.sqrt(span) * gyro_rng.standard_normal())
            roll = blend.update(t, got.roll, increment)
        previous = i
        errors.append([math.degrees(wrap_pi(a - b)) for a, b in
                       ((roll, want.roll), (got.pitch, want.pitch), (got.yaw, want.yaw))])
        kept.append(i)
    return Errors(flight.t[kept], np.array(errors), near_change[kept])


def main() -> None:
    """Print the roll, pitch, yaw error std (deg) of a grid of estimators over the flight."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate-hz", type=float, nargs="+", default=[5.0, 10.0])
    parser.add_argument("--jerk-psd", type=float, nargs="+", default=[0.02, 0.05, 0.1, 0.2, 0.5, 1.0])
    parser.add_argument("--lag-s", type=float, nargs="+", default=[0.0, 0.2, 0.4, 0.6, 1.0])
    parser.add_argument("--gyro-tau-s", type=float, nargs="+", default=[0.0],
                        help="gyro blend time constants, s (0: GNSS only)")
    parser.add_argument("--seeds", type=int, default=3, help="flights (plan and noise seeds)")
    args = parser.parse_args()
    flights = [fly(FlightPlan(seed=s)) for s in range(args.seeds)]
    print("rate_hz jerk_psd lag_s gyro_tau_s | std roll pitch yaw deg | roll std steady / manoeuvres | roll max")
    for rate, jerk, lag, tau in itertools.product(args.rate_hz, args.jerk_psd, args.lag_s, args.gyro_tau_s):
        runs = [evaluate(f, Receiver(rate_hz=rate, seed=100 + s), Estimator(jerk, lag, tau))
                for s, f in enumerate(flights)]
        err = np.concatenate([r.euler_deg for r in runs])
        trans = np.concatenate([r.transition for r in runs])
        std, steady, moving = err.std(axis=0), err[~trans, 0].std(), err[trans, 0].std()
        print(f"{rate:7.0f} {jerk:8.3f} {lag:5.1f} {tau:10.1f} | {std[0]:.3f} {std[1]:.3f} {std[2]:.3f} | "
              f"{steady:.3f} / {moving:.3f} ({trans.mean():.0%}) | {np.abs(err[:, 0]).max():.2f}")


if __name__ == "__main__":
    main()
