"""`companion bench`: per-stage timings (median, p99) of the hot paths present in this build.

Each stage runs ``repeat`` times on synthetic input and reports wall-clock milliseconds per
call on this machine. Figures in the README come from this command.
"""

from __future__ import annotations

import asyncio
import platform
import time
from collections.abc import Callable

import numpy as np

from companion.clock import realtime_event_loop
from companion.mavlink.estimate import upper_triangle
from companion.messages import PoseEstimate
from companion.mavlink.link import mavlink, nonfinite_fields
from companion.mavlink.setpoints import Setpoint, setpoint_message
from companion.telemetry.publisher import encode_json
from companion.timing import time_stage


def _estimate_output_stage() -> Callable[[], object]:
    encoder = mavlink.MAVLink(None, 1, 197)
    cov = np.diag([0.01, 0.01, 0.02, 1e-3, 1e-3, 2e-3])
    est = PoseEstimate(1.0, np.array([1.0, 2.0, -1.0]), (0.01, 0.02, 0.5), cov, np.zeros(3), np.eye(3) * 0.01)

    def stage() -> bytes:
        assert est.is_finite()
        msg = mavlink.MAVLink_vision_position_estimate_message(
            int(est.t_capture * 1e6), *map(float, est.position_ned), *est.euler_rad, upper_triangle(est.pose_covariance), 0)
        assert not nonfinite_fields(msg)
        return msg.pack(encoder)
    return stage


def _setpoint_stage() -> Callable[[], object]:
    encoder = mavlink.MAVLink(None, 1, 197)
    sp = Setpoint(position_ned=np.array([1.0, 2.0, -1.0]), velocity_ned=np.zeros(3), acceleration_ned=np.zeros(3))
    return lambda: setpoint_message(sp, 1000, (1, 1)).pack(encoder)


def _telemetry_stage() -> Callable[[], object]:
    payload = {"position_ned_m": np.array([1.0, 2.0, -1.0]), "euler_rad": (0.0, 0.0, 0.5),
               "velocity_ned_mps": np.zeros(3), "position_variance_m2": np.full(3, 0.01)}
    return lambda: encode_json(1.0, payload)


def _lidar_streams_stage() -> Callable[[], object]:
    from companion.dashboard.bench import arena_scan
    from companion.nav.lidar_streams import scan_payloads

    record, localizer = arena_scan()
    return lambda: scan_payloads(record, localizer)


def _scan_encode_stage() -> Callable[[], object]:
    from companion.dashboard.bench import arena_scan
    from companion.nav.lidar_streams import scan_payloads
    from companion.telemetry.scan_codec import encode_scan

    payload = scan_payloads(*arena_scan())["scan"]
    return lambda: encode_scan(1.0, payload)


def _sitl_physics_stage() -> Callable[[], object]:
    from sitl.copter import SimulatedCopter

    copter = SimulatedCopter(seed=0, home=(1.2966, 103.7764, 10.0))
    dt = 1.0 / SimulatedCopter.PHYSICS_HZ
    return lambda: copter.step(dt)


STAGES: dict[str, Callable[[], Callable[[], object]]] = {
    "link.vision_position_estimate (check + encode)": _estimate_output_stage,
    "link.setpoint (encode)": _setpoint_stage,
    "telemetry.pose (JSON encode)": _telemetry_stage,
    "telemetry.scan, lines, corners payloads": _lidar_streams_stage,
    "telemetry.scan (binary encode, 1081 beams)": _scan_encode_stage,
    "sitl.copter step (1/400 s)": _sitl_physics_stage,
}


DASHBOARD_SECONDS = 10.0  # measured run of the dashboard chain
WAKEUP_RATES_HZ = (50.0, 150.0)  # the nav tick alone; the real-driver hover's wake-ups (ticks, IMU, scans)
WAKEUP_SECONDS = 3.0


def wakeup_cpu_us(rate_hz: float, seconds: float) -> float:
    """CPU time (us, user + system, this thread) the daemon's real-time event loop
    (:func:`companion.clock.realtime_event_loop`) spends per wake-up when it sleeps until a timer
    ``rate_hz`` times a second for ``seconds`` and does nothing else: the fixed cost of each timer,
    datagram or scan that wakes the daemon on this machine (system call, scheduler, virtualisation,
    the interpreter's caches gone cold while it slept), before any work."""
    loop = realtime_event_loop()

    async def sleep_at_rate() -> float:
        period = 1.0 / rate_hz
        due = loop.time()
        end = due + seconds
        wakes = 0
        start = time.thread_time()
        while due < end:
            due += period
            await asyncio.sleep(max(0.0, due - loop.time()))
            wakes += 1
        return (time.thread_time() - start) / wakes * 1e6

    try:
        return loop.run_until_complete(sleep_at_rate())
    finally:
        loop.close()


def _stages_and_accuracy(stages: dict[str, tuple[float, float]], accuracy: dict[str, str]) -> None:
    """A pipeline's stage rows (median, p99 ms), then its accuracy lines."""
    for name, (median, p99) in stages.items():
        _row(name, median, p99)
    for name, text in accuracy.items():
        print(f"  {name}: {text}")


def _row(name: str, median: float, p99: float) -> None:
    print(f"{name:<50} {median:>10.4f} {p99:>10.4f}")


def run_bench(repeat: int) -> int:
    """Print every stage's median and p99 in ms: link, telemetry, SITL, the event loop's cost per
    wake-up, lidar pipeline (and how it holds with beams dropped and a tilted scanner), laser-dot
    pipeline (and its accuracy beside the markers-alone pose), EKF-SLAM, GNSS + optic flow (and the
    flow's accuracy), fusion, control;
    then the dashboard's publish-to-browser latency and CPU."""
    from companion.control.bench_control import control_figures, run_control_bench
    from companion.dashboard.bench import print_dashboard_figures
    from companion.nav.bench_fusion import run_fusion_bench
    from companion.nav.bench_robustness import robustness_figures
    from companion.nav.bench_stages import run_stage_bench
    from companion.nav.ekf_slam.bench_slam import run_slam_bench
    from companion.nav.gnss_flow.bench_flow import run_flow_bench
    from companion.nav.laser_dots.bench_dots import run_dots_bench

    print(f"companion bench: {repeat} calls per stage, Python {platform.python_version()}, "
          f"numpy {np.__version__}, {platform.machine()}")
    print(f"{'stage':<50} {'median ms':>10} {'p99 ms':>10}")
    for name, make in STAGES.items():
        _row(name, *time_stage(make(), repeat))
    costs = ", ".join(f"{wakeup_cpu_us(hz, WAKEUP_SECONDS):.0f} us at {hz:.0f} Hz" for hz in WAKEUP_RATES_HZ)
    print(f"  event loop, CPU per wake-up with no work (the daemon's loop asleep between timers): {costs}")
    print("lidar pipeline (a 1081-beam UTM-30LX scan / 682-beam URG-04LX scan of the default arena):")
    for name, (median, p99) in run_stage_bench(repeat).items():
        _row(name, median, p99)
    for name, text in robustness_figures().items():
        print(f"  {name}: {text}")
    print("laser-dot pipeline (640x480 frames of the simulated downward camera, config/sitl-laser-dots.yaml):")
    _stages_and_accuracy(*run_dots_bench(repeat))
    print("EKF-SLAM (a map of 100 landmarks, 303 states; issue 14: update <= 2 ms median):")
    for name, (median, p99) in run_slam_bench(repeat).items():
        _row(name, median, p99)
    print("GNSS + optic flow (forward 90x90 deg camera, 100 m AGL, 20 m/s, 10 Hz; issue 15: LK <= 12 ms median):")
    _stages_and_accuracy(*run_flow_bench(repeat))
    print("fusion (50 Hz Kalman filter):")
    for name, (median, p99) in run_fusion_bench(repeat).items():
        _row(name, median, p99)
    print("control (RPT outer loop vs a PID with the same closed-loop poles):")
    for name, (median, p99) in run_control_bench(repeat).items():
        _row(name, median, p99)
    for name, value in control_figures().items():
        print(f"  {name}: {_figure(value)}")
    print_dashboard_figures(DASHBOARD_SECONDS)
    return 0


def _figure(value: object) -> str:
    """Readable control figures: step (rise s, settling s, overshoot %), tracking {name: (rms m, max m)}."""
    if isinstance(value, tuple):
        rise, settle, overshoot = value
        return f"rise {rise:.2f} s, settling {settle:.2f} s, overshoot {overshoot:.1f} %"
    if isinstance(value, dict):
        return ", ".join(f"{k} RMS {rms * 1e3:.1f} mm (max {mx * 1e3:.1f})" for k, (rms, mx) in value.items())
    return f"{value:.1f}"
