"""The dashboard page in Debian's headless Chromium, against the real SITL loopback.

`make test` installs chromium (Makefile `system-deps`). Screenshots go to artifacts/ (ignored
by git) for a person to look at: the flight, the lost link, the recovery.
"""

from __future__ import annotations

import re
import socket
import subprocess
import sys
from pathlib import Path

from companion.dashboard.bench import measure_dashboard
from companion.dashboard.headless import HeadlessChromium
from sitl.harness import wait_listening
from tests.conftest import REPO, free_port
from tests.dashboard_fleet import Publishers, fleet_page
from tests.sitl_helpers import Processes, vehicle_args, wait_for, write_sitl_config
from tests.test_mavsdk_interop import SitlRun, note_children, stop_sitl

ARTIFACTS = REPO / "artifacts"
MOVED_M = 1.0  # the marker must travel this far on the map
LINK_STATE = "document.getElementById('link-badge').dataset.state"
MARKER = ("(() => { const v = document.getElementById('vehicle'); "
          "return v.dataset.north === undefined ? null : [Number(v.dataset.north), Number(v.dataset.east)]; })()")
HEALTH_ROWS = ("[...document.querySelectorAll('#health-table tbody tr')]"
               ".map((tr) => [...tr.cells].map((td) => td.textContent))")


def test_sitl_dashboard_shows_the_vehicle_moving_live(tmp_path: Path) -> None:
    http_port = free_port(socket.SOCK_STREAM)
    config = write_sitl_config(tmp_path / "sitl.yaml", vehicle_port=free_port(), gcs_port=free_port(),
                               zenoh_port=free_port(socket.SOCK_STREAM),
                               mission=str(REPO / "config" / "missions" / "survey-points.yaml"))
    output = tmp_path / "sitl.out"
    with open(output, "w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "companion.cli", "sitl", "-c", str(config), "--seconds", "120",
                                 "--dashboard", str(http_port)], cwd=REPO, stdout=out, stderr=subprocess.STDOUT)
    run = SitlRun(proc, gcs_port=0, output=output)
    try:
        note_children(run)
        url = wait_for(lambda: re.search(r"dashboard at (http://\S+)", run.text()), 30, "the dashboard's URL")[1]
        assert url == f"http://127.0.0.1:{http_port}/"
        with HeadlessChromium() as browser:
            browser.open(url)
            start = browser.wait_for(MARKER, 30, "the vehicle marker")
            rows = browser.wait_for(f"(() => {{ const r = {HEALTH_ROWS}; return r.length >= 5 && r; }})()", 30,
                                    "the health table to fill")
            assert {"link", "origin", "nav:lidar", "nav:fusion"} <= {name for name, *_ in rows}
            assert all(state in ("ok", "degraded", "lost") and reason for _, state, reason, _ in rows)
            moved = browser.wait_for(
                f"(() => {{ const p = {MARKER}; return p && Math.hypot(p[0] - {start[0]}, p[1] - {start[1]}) >= {MOVED_M} && p; }})()",
                90, f"the vehicle marker to move {MOVED_M} m")
            print(f"vehicle marker moved from {start} to {moved} (north, east m)")
            assert browser.evaluate(LINK_STATE) == "ok"
            # a scan's lines and corners arrive after the scan itself ("? lines" until then): poll
            browser.wait_for("/\\d+ matched \\((tracking|degraded)\\)/.test(document.getElementById('scan-info').textContent)",
                             5, "the scan line to show matched corners")
            assert browser.evaluate("document.querySelectorAll('#position-plots polyline').length") >= 3
            assert browser.evaluate("document.querySelector('#mission-table').textContent").count("survey-points") == 1
            sources = browser.evaluate("[...document.querySelectorAll('#sources-table tbody tr')]"
                                       ".map((r) => [...r.cells].map((c) => c.textContent))")
            assert [row[:2] for row in sources] == [["lidar", "active"]], sources
            assert "lidar: planar fixes" in browser.evaluate("document.querySelector('#system-table').textContent")
            print(f"screenshot: {browser.screenshot(ARTIFACTS / 'dashboard-sitl.png')}")
    finally:
        stop_sitl(run)


def test_the_page_shows_the_link_lost_then_recovers_without_a_reload(tmp_path: Path) -> None:
    procs = Processes(tmp_path)
    try:
        _stop_the_daemon_and_start_it_again(tmp_path, procs)
    finally:
        procs.close()


def _stop_the_daemon_and_start_it_again(tmp_path: Path, procs: Processes) -> None:
    vehicle_port, http_port = free_port(), free_port(socket.SOCK_STREAM)
    config = write_sitl_config(tmp_path / "sitl.yaml", vehicle_port=vehicle_port, gcs_port=free_port(),
                               zenoh_port=free_port(socket.SOCK_STREAM), mission=None)
    procs.start("vehicle", vehicle_args(vehicle_port, position_source="extnav", gps=False, start="1.0,1.0,0.0"))
    daemon = [sys.executable, "-m", "companion.cli", "run", "-c", str(config)]
    first = procs.start("daemon", daemon)
    dashboard = procs.start("dashboard", [sys.executable, "-m", "companion.cli", "dashboard", "-c", str(config),
                                          "--port", str(http_port)])
    assert wait_listening(dashboard, [http_port], 15), procs.output("dashboard")
    with HeadlessChromium() as browser:
        browser.open(f"http://127.0.0.1:{http_port}/")
        browser.evaluate("window.pageMark = 'loaded once'")
        browser.wait_for(f"{LINK_STATE} === 'ok'", 30, "the telemetry link to show ok")
        browser.wait_for(MARKER, 30, "the vehicle marker")

        assert Processes.stop(first) == 0  # the daemon stops (SIGTERM), the page stays open
        browser.wait_for(f"{LINK_STATE} === 'lost'", 15, "the telemetry link to show lost")
        print(f"screenshot: {browser.screenshot(ARTIFACTS / 'dashboard-link-lost.png')}")

        procs.start("daemon-again", daemon)
        browser.wait_for(f"{LINK_STATE} === 'ok'", 30, "the telemetry link to recover")
        uptime = browser.wait_for("(() => { const row = [...document.querySelectorAll('#system-table tr')]"
                                  ".find((tr) => tr.cells[0].textContent === 'uptime (s)');"
                                  " return row && Number(row.cells[1].textContent) < 15 && row.cells[1].textContent; })()",
                                  15, "the restarted daemon's system stream")
        print(f"restarted daemon up {uptime} s; screenshot: "
              f"{browser.screenshot(ARTIFACTS / 'dashboard-link-recovered.png')}")
        assert browser.evaluate("window.pageMark") == "loaded once"  # the same page: no reload
        assert browser.evaluate("performance.getEntriesByType('navigation').length") == 1


def test_each_vehicle_can_be_selected(tmp_path: Path) -> None:
    positions = {1: [1.0, 1.0, -1.0], 2: [4.0, 6.0, -1.5]}  # north, east, down m

    def tick(publishers: Publishers) -> None:  # two vehicles, each on its own zenoh endpoint, 10 Hz
        for sysid, publisher in publishers.items():
            publisher.publish("pose", {"position_ned_m": positions[sysid], "euler_rad": [0.0, 0.0, 0.0]})

    with fleet_page(tmp_path, (1, 2), tick) as browser:
        options = browser.wait_for("(() => { const o = [...document.querySelectorAll('#vehicle-select option')]"
                                   ".map((o) => o.value); return o.length === 2 && o; })()", 15, "two vehicles")
        assert options == ["1", "2"]
        for sysid in (1, 2, 1):  # whichever showed first, each one can be chosen
            browser.evaluate("(() => { const s = document.getElementById('vehicle-select');"
                             f" s.value = '{sysid}'; s.dispatchEvent(new Event('change')); }})()")
            north = positions[sysid][0]
            assert browser.wait_for(f"(() => {{ const p = {MARKER}; return p && p[0] === {north} && p; }})()", 10,
                                    f"vehicle {sysid}'s marker") == positions[sysid][:2]


def test_poses_reach_the_browser_at_their_rate_and_the_figures_are_printed() -> None:
    seconds = 4.0
    figures = measure_dashboard(seconds)
    print(f"publish-to-browser latency median {figures.latency_ms_p50:.1f} ms, p99 {figures.latency_ms_p99:.1f} ms "
          f"over {figures.poses} poses; dashboard server {figures.cpu_percent:.1f} % CPU, {figures.rss_mb:.0f} MB")
    # 10 Hz; a slow browser may see two poses merged into the newer (by design), never a stall
    assert figures.poses >= 0.8 * seconds * 10
    assert 0.0 < figures.latency_ms_p50 <= figures.latency_ms_p99
