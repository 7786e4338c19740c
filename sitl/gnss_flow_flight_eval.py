"""The whole ``gnss_flow`` pipeline offline over the manoeuvring flight of
:mod:`.pseudo_attitude_eval`, on the synthetic flow path (sitl/flow_sim.py: the seed's 45 x 45
flow over 90 x 90 deg, +/-2.5 deg angle noise, looking along body x, 10 Hz): its Euler errors
against the airframe's truth, with the autopilot's IMU (gyro derotation and, at
``gyro_roll_tau_s`` above 0, the gyro roll blend) or without (GNSS-derived rates).
``python -m sitl.gnss_flow_flight_eval`` prints the table; tests/test_gnss_pseudo_attitude_eval.py
runs a short flight.

Timing, as in the daemon: GNSS fixes at ``Receiver.rate_hz`` stamped at their epoch and
arriving ``latency_s`` later; flow fields arriving 5 ms after their later instant; IMU samples at
``IMU_RATE_HZ``; a nav cycle (``step``) after every message. The IMU's gyro carries the
:class:`.pseudo_attitude_eval.Gyro` errors on every axis (bias, scale, white noise); its
accelerometer is exact (the coordination check).

Frames: NED, flat ground at D = 0 (the flight starts 100 m above it), body FRD with x along the
air velocity (still air, no angle of attack); Euler ZYX; errors in degrees, estimate minus truth
at each estimate's ``t_capture``.
"""

from __future__ import annotations

import argparse
import logging
import math
import numpy as np

from companion.frames import GRAVITY_MPS2, quat_from_euler, rotation_from_euler, wrap_pi
from companion.health import Health
from companion.messages import GNSS_3D, AttitudeEstimate, GnssFix, ImuSample
from companion.nav.gnss_flow.config import GnssFlowConfig
from companion.nav.gnss_flow.pipeline import GnssFlowPipeline
from companion.nav.gnss_flow.pseudo_attitude import body_rates_from_euler_rates
from sitl.pseudo_attitude_eval import Errors, Flight, FlightPlan, Gyro, Receiver, fly, manoeuvring
from drivers.mount import Mount
from sitl.flow_sim import SimFlowSettings, SimulatedFlowSensor
from sitl.truth import TruthSample

FLOW_HZ = 10.0  # the flow sensor's fields
IMU_RATE_HZ = 50.0
FLOW_LATENCY_S = 0.005


def _index(flight: Flight, t: float) -> int:
    return int(round(t / float(flight.t[1] - flight.t[0])))


def _truth(flight: Flight, i: int) -> TruthSample:
    return TruthSample(float(flight.t[i]), flight.position_ned[i], flight.velocity_ned[i],
                       quat_from_euler(*(float(a) for a in flight.euler[i])))


def _imu(flight: Flight, i: int, gyro: Gyro, rng: np.random.Generator) -> ImuSample:
    roll, pitch, yaw = (float(a) for a in flight.euler[i])
    rates = body_rates_from_euler_rates(roll, pitch, flight.euler_rates[i])
    noise = math.radians(gyro.noise_dps_rthz) * math.sqrt(IMU_RATE_HZ) * rng.standard_normal(3)
    measured = (1.0 + gyro.scale_error) * rates + math.radians(gyro.bias_dps) + noise
    specific_force = rotation_from_euler(roll, pitch, yaw).T @ (flight.acceleration_ned[i]
                                                                 - np.array([0.0, 0.0, GRAVITY_MPS2]))
    return ImuSample(float(flight.t[i]), specific_force, measured)


def run(flight: Flight, cfg: GnssFlowConfig, receiver: Receiver = Receiver(), gyro: Gyro | None = None,
        settle_s: float = 10.0) -> Errors:
    """The Euler errors of the attitude estimates (from ``settle_s`` on) of the pipeline of ``cfg``
    (its ``gnss`` "gps", ``flow`` "of", ``imu_sensor`` "imu" or None) flown over ``flight``,
    ``transition`` marking those in a manoeuvre; ``gyro`` is the IMU's when ``cfg.imu_sensor`` is
    set."""
    pipeline = GnssFlowPipeline(cfg, None, None, Health(lambda: 0.0), Mount(np.eye(3), np.zeros(3)))
    sensor = SimulatedFlowSensor("of", SimFlowSettings(seed=receiver.seed), Mount(np.eye(3), np.zeros(3)), None)
    rng = np.random.default_rng(receiver.seed)
    end = float(flight.t[-1])
    events = [(k / receiver.rate_hz + receiver.latency_s, 0, k / receiver.rate_hz)
              for k in range(int(end * receiver.rate_hz) + 1)]
    events += [(k / FLOW_HZ + FLOW_LATENCY_S, 1, k / FLOW_HZ) for k in range(1, int(end * FLOW_HZ) + 1)]
    if cfg.imu_sensor is not None:
        events += [(k / IMU_RATE_HZ, 2, k / IMU_RATE_HZ) for k in range(int(end * IMU_RATE_HZ) + 1)]
    estimates: list[AttitudeEstimate] = []
    for arrival, kind, t in sorted(events):
        if arrival > end:
            break
        i = _index(flight, t)
        if kind == 0:
            velocity = flight.velocity_ned[i] + rng.normal(0.0, receiver.doppler_sigma_mps, 3)
            pipeline.on_fix(GnssFix("gps", t, GNSS_3D, 0.0, 0.0, 0.0, velocity_ned_mps=velocity,
                                    speed_acc_mps=receiver.doppler_sigma_mps))
        elif kind == 1:
            j = _index(flight, t - 1.0 / FLOW_HZ)
            pipeline.on_flow(sensor.field(float(flight.t[j]), t, _truth(flight, j), _truth(flight, i), i))
        else:
            pipeline.on_imu(_imu(flight, i, gyro or Gyro(), rng))
        estimates += [e for e in pipeline.step(arrival) if isinstance(e, AttitudeEstimate) and e.t_capture >= settle_s]
    indices = [_index(flight, e.t_capture) for e in estimates]
    errors = [[math.degrees(wrap_pi(a - b)) for a, b in zip(e.euler_rad, flight.euler[i])]
              for e, i in zip(estimates, indices)]
    return Errors(np.array([e.t_capture for e in estimates]), np.array(errors), manoeuvring(flight)[indices])


def main() -> None:
    """Print the Euler error std of the pipeline over the flight, with and without the IMU."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration-s", type=float, default=300.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rate-hz", type=float, default=5.0, help="GNSS fix rate")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="GnssFlowConfig fields (floats) instead of their defaults")
    args = parser.parse_args()
    logging.getLogger("companion.health").setLevel(logging.ERROR)  # the path's refusals, counted anyway
    flight = fly(FlightPlan(duration_s=args.duration_s, seed=args.seed))
    overrides = {k: float(v) for k, v in (item.split("=") for item in args.set)}
    print("IMU   | std roll pitch yaw deg | mean | roll std steady / manoeuvres | estimates")
    for imu in (None, "imu"):
        cfg = GnssFlowConfig(gnss="gps", flow="of", imu_sensor=imu, **overrides)  # type: ignore[arg-type]
        r = run(flight, cfg, Receiver(rate_hz=args.rate_hz), Gyro())
        std, mean = r.euler_deg.std(axis=0), r.euler_deg.mean(axis=0)
        print(f"{'gyro' if imu else 'none':5} | {std[0]:.3f} {std[1]:.3f} {std[2]:.3f} | "
              f"{mean[0]:+.3f} {mean[1]:+.3f} {mean[2]:+.3f} | {r.std(~r.transition)[0]:.3f} / "
              f"{r.std(r.transition)[0]:.3f} | {len(r.t)}")


if __name__ == "__main__":
    main()
