"""The flight report's ``attitude`` block (issue 15): attitude-only estimates and heights above
ground scored against the simulator's truth, per source, with the contract's names filled from
the GNSS + optic-flow sources."""

from __future__ import annotations

import json
import math
from collections.abc import Callable

import numpy as np
import pytest

from companion.frames import wrap_pi
from companion.mavlink.distance import ORIENTATION
from companion.mavlink.link import mavlink
from sitl.ardupilot_observer import ArduPilotObserver
from sitl.flight_log import FlightLog
from sitl.report import AGL_CEILING_M, build_report, distance_capture_times

TRUTH_HZ = 50.0


def true_euler(t: float, yaw0: float = 0.3) -> tuple[float, float, float]:
    """A banking, pitching, turning flight's true attitude (rad) at t s; yaw wrapped to [-pi, pi)."""
    return (math.radians(20.0) * math.sin(0.3 * t), math.radians(8.0) * math.sin(0.17 * t + 1.0),
            float(wrap_pi(yaw0 + 0.05 * t)))


def flight_log(seconds: float, *, monotonic_at_sim_zero: float | None = None,
               height: Callable[[float], float] = lambda t: 30.0,
               euler: Callable[[float], tuple[float, float, float]] = true_euler) -> FlightLog:
    """A log whose truth flies north at 20 m/s at ``height(t)`` m with attitude ``euler(t)``."""
    log = FlightLog(seed=1, lockstep=monotonic_at_sim_zero is None, monotonic_at_sim_zero=monotonic_at_sim_zero)
    for t in np.arange(0.0, seconds + 1e-9, 1.0 / TRUTH_HZ):
        log.sample(float(t), truth_pos=(20.0 * t, 0.0, -height(t)), truth_vel=(20.0, 0.0, 0.0),
                   truth_euler=euler(t), est_valid=False, est_pos=(math.nan,) * 3)
    return log


def check(source: str, t_daemon: float, euler_rad: tuple[float | None, ...]) -> dict:
    """An ``attitude_check`` payload as the harness receives it (JSON: NaN is null)."""
    return json.loads(json.dumps({"v": 1, "t": t_daemon + 0.01, "source": source, "t_capture": t_daemon,
                                  "euler_rad": euler_rad, "autopilot_euler_rad": [0.0, 0.0, 0.0],
                                  "difference_deg": 0.0}))


def report(log: FlightLog, checks: list[dict], seconds: float,
           ground_height: Callable[[float, float], float] = lambda n, e: 0.0) -> dict:
    """build_report of ``log`` (through JSON, as the harness reads it) and the ``checks`` payloads."""
    return build_report(mission="table1", seconds=seconds, lockstep=log.lockstep, seed=1, control_law="guided",
                        log=json.loads(json.dumps(log.to_dict(seconds))), telemetry={}, origin=(0.0, 0.0, 0.0),
                        cpu_percent=None, rss_mb=None, attitude_checks=checks, ground_height=ground_height)


def test_a_known_bias_and_noise_come_out_as_the_mean_and_std_per_axis() -> None:
    rng = np.random.default_rng(3)
    bias_deg, sigma_deg = np.array([0.5, -0.3, 1.0]), np.array([0.2, 0.3, 0.4])
    t0 = 5000.0  # real time: the daemon's monotonic clock at sim zero
    log = flight_log(300.0, monotonic_at_sim_zero=t0)
    checks = []
    for t in np.arange(1.013, 299.0, 0.1):  # capture times between truth samples
        error = np.radians(bias_deg + sigma_deg * rng.standard_normal(3))
        checks.append(check("gnss_flow", t0 + t, tuple(float(wrap_pi(a)) for a in np.add(true_euler(t), error))))
    attitude = report(log, checks, 300.0)["attitude"]
    assert attitude["euler_mean_deg"] == pytest.approx(bias_deg, abs=0.03)
    assert attitude["euler_std_deg"] == pytest.approx(sigma_deg, rel=0.06)
    assert attitude["sources"]["gnss_flow"]["count"] == len(checks)
    assert attitude["sources"]["gnss_flow"]["euler_std_deg"] == attitude["euler_std_deg"]


def test_a_yaw_through_plus_minus_180_deg_gives_the_small_wrapped_error() -> None:
    def across_180(t: float) -> tuple[float, float, float]:
        return 0.0, 0.0, float(wrap_pi(math.pi + 0.3 * math.sin(0.5 * t)))

    log = flight_log(60.0, euler=across_180)
    bias = math.radians(2.0)
    checks = [check("gnss_flow", t, (0.0, 0.0, float(wrap_pi(across_180(t)[2] + bias))))
              for t in np.arange(0.5, 59.5, 0.1)]
    assert {math.copysign(1.0, c["euler_rad"][2]) for c in checks} == {-1.0, 1.0}  # it does cross
    attitude = report(log, checks, 60.0)["attitude"]
    assert attitude["euler_mean_deg"][2] == pytest.approx(2.0, abs=0.01)
    assert attitude["euler_std_deg"][2] < 0.01


def test_absent_sources_and_unmeasured_angles_are_null_and_no_estimates_no_block() -> None:
    log = flight_log(20.0)
    only_images = [check("gnss_flow.images", t, (*true_euler(t)[:2], None)) for t in np.arange(1.0, 19.0, 0.5)]
    attitude = report(log, only_images, 20.0)["attitude"]
    assert attitude["euler_mean_deg"] is None and attitude["euler_std_deg"] is None
    assert attitude["images_euler_std_deg"][:2] == pytest.approx([0.0, 0.0], abs=1e-3)
    assert attitude["images_euler_std_deg"][2] is None  # the yaw was never measured
    assert attitude["agl_error_pct"] is None and attitude["agl_count"] == 0
    assert set(attitude["sources"]) == {"gnss_flow.images"}
    assert "attitude" not in report(log, [], 20.0)


def test_estimates_outside_the_truth_are_not_scored() -> None:
    log = flight_log(10.0)
    checks = [check("other", t, true_euler(t)) for t in (-1.0, 5.0, 11.0)]
    assert report(log, checks, 10.0)["attitude"]["sources"]["other"]["count"] == 1


def descent(t: float) -> float:
    """A commanded descent: 80 m to 10 m over 140 s."""
    return 80.0 - 0.5 * t


def test_the_height_error_is_the_rms_of_error_over_true_height_below_50_m() -> None:
    t0 = 5.0e6  # the daemon clock in ms is past 2^32: DISTANCE_SENSOR's time_boot_ms has wrapped
    log = flight_log(140.0, monotonic_at_sim_zero=t0, height=descent)
    ground = 2.0  # the world's floor is 2 m high under the whole track
    relative = {}
    for k, t in enumerate(np.arange(1.0, 139.0, 0.2)):
        true_height = descent(t) - ground
        relative[t] = 0.04 if k % 2 else -0.06  # alternately 4 % high and 6 % low
        if true_height > AGL_CEILING_M:
            relative[t] = 3.0  # not scored: above the ceiling
        roll, pitch, _ = true_euler(t)  # the sensor looks along the body z axis: a slant distance
        distance_cm = round(true_height * (1 + relative[t]) / (math.cos(roll) * math.cos(pitch)) * 100)
        capture_ms = int((t0 + t) * 1e3) & 0xFFFFFFFF
        log.add_distance_sensor(t + 0.15, capture_ms, 0, ORIENTATION["down"], distance_cm, 10, 100000)
        log.add_distance_sensor(t + 0.15, capture_ms, 1, ORIENTATION["forward"], 50, 10, 100000)  # not a height
    attitude = report(log, [], 140.0, ground_height=lambda n, e: ground)["attitude"]
    scored = [r for r in relative.values() if r != 3.0]
    assert attitude["agl_count"] == len(scored)
    assert attitude["agl_error_pct"] == pytest.approx(100.0 * math.sqrt(np.mean(np.square(scored))), rel=1e-3)
    assert attitude["euler_mean_deg"] is None and attitude["sources"] == {}


def test_distance_capture_times_undo_the_32_bit_millisecond_wrap() -> None:
    log = FlightLog(seed=1, lockstep=False, monotonic_at_sim_zero=4_294_967.0)  # 2^32 ms, less 0.296 s
    log.add_distance_sensor(12.5, int((4_294_967.0 + 12.4) * 1e3) & 0xFFFFFFFF, 0, ORIENTATION["down"], 100, 10, 4000)
    assert distance_capture_times(log.to_dict(20.0)) == pytest.approx([12.4], abs=1e-6)


def test_a_log_without_distance_records_scores_no_height() -> None:
    log = flight_log(10.0).to_dict(10.0)
    del log["distance_sensor"]  # an older flight log
    result = build_report(mission="m", seconds=10.0, lockstep=True, seed=1, control_law="guided", log=log,
                          telemetry={}, origin=(0.0, 0.0, 0.0), cpu_percent=None, rss_mb=None,
                          attitude_checks=[check("gnss_flow", 5.0, true_euler(5.0))],
                          ground_height=lambda n, e: 0.0)
    assert result["attitude"]["agl_error_pct"] is None


def test_the_ardupilot_tap_logs_distance_sensor_as_the_built_in_vehicle_does() -> None:
    observer = ArduPilotObserver(serial0_port=0, serial1_port=0, seed=1)  # nothing started: only the log
    msg = mavlink.MAVLink_distance_sensor_message(1234, 10, 4000, 1520, mavlink.MAV_DISTANCE_SENSOR_LASER, 0,
                                                  ORIENTATION["down"], 255)
    observer._tapped(3.5, "to_autopilot", msg)
    record = observer.log.to_dict(4.0)["distance_sensor"]
    assert record == {"t_rx": [3.5], "time_boot_ms": [1234], "id": [0], "orientation": [ORIENTATION["down"]],
                      "distance_m": [15.2], "min_m": [0.1], "max_m": [40.0]}


def test_the_alarm_and_the_uncoordinated_pairs_come_out_as_intervals_of_simulation_time() -> None:
    log = flight_log(60.0)
    checks = [check("gnss_flow", t, true_euler(t)) | {"alarm": 20.0 <= t <= 24.0} for t in (k / 10 for k in range(10, 500))]
    pairs = [{"t_capture": t, "coordinated": not (30.0 <= t <= 35.0 or 40.0 <= t <= 40.2)}
             for t in (k / 5 for k in range(5, 250))]
    result = build_report(mission="table1", seconds=60.0, lockstep=True, seed=1, control_law="guided",
                          log=json.loads(json.dumps(log.to_dict(60.0))), telemetry={}, origin=(0.0, 0.0, 0.0),
                          cpu_percent=None, rss_mb=None, attitude_checks=checks, ground_height=lambda n, e: 0.0,
                          pair_streams={"gnss_flow": pairs, "gnss_flow_images": []})
    source = result["attitude"]["sources"]["gnss_flow"]
    assert source["alarm_intervals_s"] == [[20.0, 24.0]]
    assert source["uncoordinated_intervals_s"] == [[30.0, 35.0], [40.0, 40.2]]
