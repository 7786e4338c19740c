"""The dashboard's figures: publish-to-browser latency and the dashboard server's CPU.

A real chain on loopback: this process publishes like the daemon (a :class:`TelemetryPublisher`
on its own zenoh peer; pose at 10 Hz, the scan with its lines and corners at 5 Hz, status
streams at 1 Hz), ``companion dashboard`` runs as its own process, and a headless Chromium
opens the page. Latency is from ``publish()`` (the pose's ``t``, this process's monotonic
clock) to the arrival of that pose in the browser's JavaScript (an EventSource beside the
page's own, stamped with the browser's clock; both clocks are this machine's, aligned through
the wall clock). CPU is the dashboard process's user + system time over the run.
"""

from __future__ import annotations

import math
import socket
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from companion.dashboard.app import spawn_dashboard
from companion.dashboard.headless import HeadlessChromium, find_chromium
from companion.nav.bench_stages import DEFAULT_WORLD, make_mount, synthetic_scan
from companion.nav.lidar_streams import ProcessedScan, map_payload, scan_payloads
from companion.nav.planar import Mount2D, PlanarLocalizer
from companion.telemetry.publisher import TelemetryPublisher
from companion.telemetry.session import open_session
from drivers.lidar_models import UTM_30LX
from sitl.harness import process_cpu_rss
from sitl.raycast import WorldGeometry
from companion.world import load_world

POSE_HZ = 10.0
SCAN_HZ = 5.0
WARM_UP_S = 2.0  # before measuring: routes, page load, first scans
PROBE = """
window.latencyProbe = [];
new EventSource("/events").onmessage = (m) => {
  const e = JSON.parse(m.data);
  if (e.type === "sample" && e.stream === "pose") window.latencyProbe.push([e.data.t, performance.timeOrigin + performance.now()]);
};
"""


@dataclass
class DashboardFigures:
    """Latency from publish() to the browser (ms) and the dashboard process's CPU and memory."""

    latency_ms_p50: float
    latency_ms_p99: float
    poses: int  # poses measured
    cpu_percent: float  # of one core, dashboard process, over the measured run
    rss_mb: float  # its peak resident memory


def arena_scan(pose: tuple[float, float, float] = (2.0, 2.0, math.radians(30.0))) -> tuple[ProcessedScan, PlanarLocalizer]:
    """A 1081-beam UTM-30LX scan of the default arena from ``pose`` (x m, y m, yaw rad) at 1 m
    height, processed by a localizer of the arena map, as the lidar pipeline leaves it."""
    world = load_world(DEFAULT_WORLD)
    scan = synthetic_scan(WorldGeometry.from_world(world), UTM_30LX, make_mount((0.0, 0.0, -0.1), (0.0, 0.0, 0.0)),
                          np.array([pose[0], pose[1], -1.0]), (0.0, 0.0, pose[2]), np.random.default_rng(1), 0.01)
    localizer = PlanarLocalizer(world.corner_array(), world.wall_angle_deg, mount=Mount2D(z_m=-0.1),
                                walls=world.segments_at(1.1), initial_pose=pose)
    fix = localizer.update(scan)
    assert localizer.last_lines is not None and localizer.last_corners is not None
    return ProcessedScan(scan, 0.0, 0.0, fix, localizer.last_lines, localizer.last_corners), localizer


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure_dashboard(seconds: float, work_dir: Path | None = None) -> DashboardFigures:
    """Run the chain for ``seconds`` after a warm-up and measure it (needs Chromium).

    Raises:
        companion.dashboard.headless.BrowserError: no Chromium, or it failed.
        RuntimeError: the dashboard did not start, or no pose reached the browser.
    """
    zenoh_port = free_tcp_port()
    with tempfile.TemporaryDirectory(prefix="companion-dashboard-bench-") as tmp:
        config = Path(work_dir or tmp) / "dashboard-bench.yaml"
        config.write_text(yaml.safe_dump({"origin": {"lat": 0.0, "lon": 0.0, "alt": 0.0},
                                          "telemetry": {"listen": [f"tcp/127.0.0.1:{zenoh_port}"]}}))
        session = open_session("peer", [f"tcp/127.0.0.1:{zenoh_port}"], [], False, False)
        publisher = TelemetryPublisher(session, sysid=1, clock=time.monotonic)
        dashboard = None
        try:
            dashboard, url = spawn_dashboard(config, 0, extra_args=("--log-level", "warning"))
            with HeadlessChromium() as browser:
                browser.open(url)
                browser.evaluate(PROBE)
                _publish_for(publisher, WARM_UP_S)
                start_t = time.monotonic()
                before = process_cpu_rss(dashboard.pid)
                _publish_for(publisher, seconds)
                after = process_cpu_rss(dashboard.pid)
                elapsed = time.monotonic() - start_t
                time.sleep(0.3)  # the last poses on their way
                received = browser.evaluate("window.latencyProbe")
        finally:
            publisher.close()
            if dashboard is not None:
                dashboard.terminate()
                dashboard.wait(10)
            session.close()
    wall_minus_monotonic = time.time() - time.monotonic()  # both clocks of this machine
    latencies = [browser_ms - (t + wall_minus_monotonic) * 1e3 for t, browser_ms in received if t >= start_t]
    if not latencies or before is None or after is None:
        raise RuntimeError("no pose reached the browser during the run")
    return DashboardFigures(float(np.median(latencies)), float(np.percentile(latencies, 99)), len(latencies),
                            100.0 * (after[0] - before[0]) / elapsed, after[1])


def _publish_for(publisher: TelemetryPublisher, seconds: float) -> None:
    """Publish like a flying daemon for ``seconds``: pose 10 Hz, scan streams 5 Hz, status 1 Hz."""
    record, localizer = arena_scan()
    scan_streams = scan_payloads(record, localizer)
    start = time.monotonic()
    tick = 0
    while (now := time.monotonic()) - start < seconds:
        angle = 0.2 * (now - start)
        publisher.publish("pose", {"position_ned_m": [2.0 + math.cos(angle), 2.0 + math.sin(angle), -1.0],
                                   "euler_rad": [0.0, 0.0, angle + math.pi / 2], "velocity_ned_mps": None,
                                   "position_variance_m2": [1e-4, 1e-4, 4e-4], "yaw_variance_rad2": 1e-6,
                                   "t_capture": now, "source": "bench"})
        if tick % round(POSE_HZ / SCAN_HZ) == 0:
            for stream, payload in scan_streams.items():
                publisher.publish(stream, payload)
        if tick % round(POSE_HZ) == 0:
            publisher.publish("health", {"overall": "ok", "components": {}, "tasks": {}})
            publisher.publish("rates", {"streams": publisher.stats()})
            publisher.publish("map", map_payload(localizer))
        tick += 1
        time.sleep(max(0.0, start + tick / POSE_HZ - time.monotonic()))


def print_dashboard_figures(seconds: float) -> None:
    """The bench's dashboard section (skipped, saying why, without Chromium)."""
    print(f"dashboard ({POSE_HZ:g} Hz pose + {SCAN_HZ:g} Hz scans with lines and corners, {seconds:g} s; "
          "zenoh -> companion dashboard -> headless Chromium, loopback):")
    if find_chromium() is None:
        print("  skipped: no Chromium (Debian: apt-get install chromium)")
        return
    figures = measure_dashboard(seconds)
    print(f"  publish-to-browser latency: median {figures.latency_ms_p50:.1f} ms, p99 {figures.latency_ms_p99:.1f} ms "
          f"over {figures.poses} poses")
    print(f"  dashboard server: {figures.cpu_percent:.1f} % of one core, {figures.rss_mb:.0f} MB peak")
