"""`companion dashboard` without a browser: a real process joined to a real zenoh publisher,
read over HTTP and server-sent events like the page reads it."""

from __future__ import annotations

import http.client
import json
import re
import socket
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from companion.config import TelemetryConfig
from companion.dashboard.app import dashboard_endpoints, page_url, spawn_dashboard
from companion.dashboard.bench import arena_scan
from companion.dashboard.hub import Browser, decode_payload
from companion.nav.lidar_streams import map_payload, scan_payloads
from companion.telemetry.publisher import TelemetryPublisher
from companion.telemetry.scan_codec import SCAN_ENCODING, encode_scan
from companion.telemetry.session import open_session
from tests.conftest import REPO, free_port
from tests.gnss_flow_telemetry import flight

pytestmark = pytest.mark.timeout(60)

STATIC = REPO / "companion" / "dashboard" / "static"


@dataclass
class Dashboard:
    url: str
    host: str
    port: int
    endpoint: str  # the zenoh endpoint it connects to (a publisher listens there)


@pytest.fixture
def dashboard(tmp_path: Path) -> Iterator[Dashboard]:
    endpoint = f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"
    config = tmp_path / "ground.yaml"
    config.write_text(yaml.safe_dump({"origin": {"lat": 0.0, "lon": 0.0, "alt": 0.0},
                                      "telemetry": {"listen": [endpoint]}}))
    proc, url = spawn_dashboard(config, 0)  # any free port: the URL says which
    host, port = re.match(r"http://(127\.0\.0\.1):(\d+)/$", url).groups()  # type: ignore[union-attr]
    try:
        yield Dashboard(url, host, int(port), endpoint)
    finally:
        proc.terminate()
        assert proc.wait(10) == 0  # SIGTERM: a clean exit


class EventStream:
    """The page's view: GET /events, one JSON event per ``data:`` line."""

    def __init__(self, dashboard: Dashboard) -> None:
        self.conn = http.client.HTTPConnection(dashboard.host, dashboard.port, timeout=5)
        self.conn.request("GET", "/events")
        self.response = self.conn.getresponse()
        assert self.response.status == 200
        assert self.response.getheader("Content-Type") == "text/event-stream"

    def events_until(self, done: Callable[[list[dict]], bool], timeout_s: float) -> list[dict]:
        """Events read until ``done(events so far)`` holds; fails after ``timeout_s``."""
        events: list[dict] = []
        deadline = time.monotonic() + timeout_s
        while not done(events):
            if time.monotonic() > deadline:
                pytest.fail(f"events so far did not satisfy the test: {[e.get('stream', e['type']) for e in events]}")
            line = self.response.fp.readline()
            if line.startswith(b"data: "):
                events.append(json.loads(line[6:]))
        return events

    def close(self) -> None:
        self.conn.close()


def streams_of(events: list[dict]) -> set[str]:
    return {e["stream"] for e in events if e["type"] == "sample"}


def test_a_new_browser_gets_the_current_state_at_once(dashboard: Dashboard) -> None:
    record, localizer = arena_scan()
    session = open_session("peer", [dashboard.endpoint], [], False, False)
    telemetry = TelemetryPublisher(session, sysid=3)
    telemetry.add_streams(("laser_dots",))  # a pipeline's own stream: the hub knows no list of them
    first = EventStream(dashboard)
    try:
        def publish_all() -> None:
            telemetry.publish("pose", {"position_ned_m": [1.0, 2.0, -1.0], "euler_rad": [0.0, 0.0, 0.5]})
            telemetry.publish("health", {"overall": "ok", "components": {"link": {"state": "ok", "reason": "x", "since": 0}}})
            telemetry.publish("alerts", {"severity": 4, "text": "companion: nav:lidar degraded"})
            for stream, payload in scan_payloads(record, localizer).items():
                telemetry.publish(stream, payload)
            telemetry.publish("map", map_payload(localizer))
            telemetry.publish("laser_dots", {"kind": "tilt", "status": "no floor marker in view", "tilt": [1.2, 0.0, 0.0]})
            session.put("uav/3/Not-A-Stream", b"{}")  # not a stream name: ignored

        deadline = time.monotonic() + 15
        while "map" not in streams_of(first.events_until(lambda e: len(e) >= 1, 5)):
            assert time.monotonic() < deadline, "the dashboard never got the publisher's samples"
            publish_all()
        first.close()
        time.sleep(0.5)  # nothing is published from here on

        second = EventStream(dashboard)
        wanted = {"pose", "health", "alerts", "scan", "lines", "corners", "map", "laser_dots"}
        events = second.events_until(lambda e: wanted <= streams_of(e), 3.0)
        second.close()
    finally:
        telemetry.close()
        session.close()
    assert events[0]["type"] == "status" and "3" in events[0]["vehicles"]
    samples = {e["stream"]: e for e in events if e["type"] == "sample"}
    assert samples["pose"]["key"] == "uav/3/pose" and samples["pose"]["sysid"] == 3
    assert samples["pose"]["data"]["position_ned_m"] == [1.0, 2.0, -1.0]
    scan = samples["scan"]["data"]
    assert len(scan["ranges_mm"]) == 1081 and scan["sequence"] == samples["lines"]["data"]["sequence"]
    assert samples["alerts"]["data"]["text"] == "companion: nav:lidar degraded"
    assert samples["laser_dots"]["key"] == "uav/3/laser_dots" and samples["laser_dots"]["data"]["tilt"] == [1.2, 0.0, 0.0]
    streams = events[0]["vehicles"]["3"]["streams"]
    assert streams["pose"]["count"] >= 1 and streams["pose"]["bad"] == 0
    assert streams["laser_dots"]["count"] >= 1 and "Not-A-Stream" not in streams


def test_the_gnss_flow_streams_and_each_sources_attitude_check_reach_a_new_browser(dashboard: Dashboard) -> None:
    """The real pipeline's two flow streams, and its two sources' cross-checks published back to back
    on the one ``attitude_check`` key: a browser joining later gets each source's, not only the last."""
    telemetry = flight(0.0)
    session = open_session("peer", [dashboard.endpoint], [], False, False)
    publisher = TelemetryPublisher(session, sysid=4)
    publisher.add_streams(tuple(telemetry.streams))  # the pipeline's telemetry_streams
    first = EventStream(dashboard)
    try:
        deadline = time.monotonic() + 15
        seen: set[str] = set()
        while not {"gnss_flow", "gnss_flow_images"} <= seen:
            assert time.monotonic() < deadline, "the dashboard never got the publisher's samples"
            for stream, payload in telemetry.streams.items():
                publisher.publish(stream, payload)
            for check in telemetry.checks:
                publisher.publish("attitude_check", check)
            seen |= streams_of(first.events_until(lambda e: len(e) >= 1, 5))
        first.close()
        time.sleep(0.5)  # everything published has arrived

        second = EventStream(dashboard)
        checks: dict[str, dict] = {}

        def complete(events: list[dict]) -> bool:
            checks.update({e["data"]["source"]: e["data"] for e in events if e.get("stream") == "attitude_check"})
            return {"gnss_flow", "gnss_flow_images"} <= streams_of(events) and len(checks) == 2
        events = second.events_until(complete, 3.0)
        second.close()
    finally:
        publisher.close()
        session.close()
    samples = {e["stream"]: e["data"] for e in events if e["type"] == "sample"}
    for stream, payload in telemetry.streams.items():
        assert set(samples[stream]) == set(payload) | {"v", "t"}
    sensor, camera = samples["gnss_flow"], samples["gnss_flow_images"]
    depth = telemetry.streams["gnss_flow"]["flow_depth_m"]
    assert len(sensor["flow_n"]) == len(sensor["flow_depth_m"]) == len(depth)
    assert [d is None for d in sensor["flow_depth_m"]] == np.isnan(depth).tolist()  # NaN arrives as null
    assert camera["foe_px"] == pytest.approx(list(telemetry.streams["gnss_flow_images"]["foe_px"]))
    assert sorted(checks) == ["gnss_flow", "gnss_flow.images"]
    for sent in telemetry.checks:
        assert checks[sent["source"]]["autopilot_euler_rad"] == pytest.approx(list(sent["autopilot_euler_rad"]))


def _request(dashboard: Dashboard, method: str, path: str, host: str | None = None) -> http.client.HTTPResponse:
    conn = http.client.HTTPConnection(dashboard.host, dashboard.port, timeout=5)
    headers = {"Host": host} if host else {}
    conn.request(method, path, headers=headers)
    response = conn.getresponse()
    response.read()
    conn.close()
    return response


def test_it_serves_its_page_and_nothing_else(dashboard: Dashboard) -> None:
    page = _request(dashboard, "GET", "/")
    assert page.status == 200 and page.getheader("Content-Type") == "text/html; charset=utf-8"
    assert "default-src 'self'" in page.getheader("Content-Security-Policy", "")
    assert _request(dashboard, "GET", "/static/app.js").getheader("Content-Type") == "text/javascript; charset=utf-8"
    assert _request(dashboard, "GET", "/static/style.css").status == 200
    assert _request(dashboard, "HEAD", "/").status == 200
    for path in ("/static/../app.py", "/static/%2e%2e/app.py", "/app.py", "/state"):
        assert _request(dashboard, "GET", path).status == 404, path
    for method in ("POST", "PUT", "DELETE"):
        assert _request(dashboard, method, "/events").status == 405  # read-only: no command path
    assert _request(dashboard, "GET", "/", host="attacker.example:8080").status == 403  # DNS rebinding
    assert _request(dashboard, "GET", "/", host=f"localhost:{dashboard.port}").status == 200


def test_it_serves_an_icon_so_the_browser_console_shows_no_404(dashboard: Dashboard) -> None:
    assert '<link rel="icon" href="/static/favicon.svg"' in (STATIC / "index.html").read_text()
    for path in ("/static/favicon.svg", "/favicon.ico"):  # the linked icon, and where browsers look without a link
        icon = _request(dashboard, "GET", path)
        assert icon.status == 200 and icon.getheader("Content-Type") == "image/svg+xml", path


def test_assets_are_self_contained_package_data() -> None:
    files = {p.name for p in STATIC.iterdir()}
    assert all(p.is_file() for p in STATIC.iterdir())  # `static/*` in pyproject covers them all
    package_data = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    assert "static/*" in package_data["companion.dashboard"]
    for asset in STATIC.iterdir():
        text = asset.read_text()
        assert not re.search(r"https?://(?!www\.w3\.org/2000/svg)", text), f"{asset.name} reaches outside the package"
        for ref in re.findall(r'(?:src|href)="/static/([^"]+)"|from "\./([^"]+)"', text):
            assert (ref[0] or ref[1]) in files, f"{asset.name} refers to a missing {ref}"


def test_undecodable_samples_are_counted_not_forwarded() -> None:
    record, localizer = arena_scan()
    scan = decode_payload(SCAN_ENCODING, encode_scan(1.0, scan_payloads(record, localizer)["scan"]))
    assert len(scan["ranges_mm"]) == 1081 and isinstance(scan["ranges_mm"][0], int)
    assert decode_payload("application/json", b'{"a": 1}') == {"a": 1}
    for encoding, payload in [("application/json", b"[1, 2]"), ("application/json", b'{"x": NaN}'),
                              ("application/json", b"\xff{"), ("text/plain", b"{}"), (SCAN_ENCODING, b"\x01\x02")]:
        with pytest.raises(ValueError):
            decode_payload(encoding, payload)


def test_a_slow_browser_keeps_the_newest_event_per_key() -> None:
    browser = Browser(size=3)
    browser.offer("uav/1/pose", "pose 1")
    browser.offer("uav/1/health", "health 1")
    browser.offer("uav/1/pose", "pose 2")  # replaces the unsent pose, keeps its place
    assert browser.take() == ["pose 2", "health 1"] and not browser.wake.is_set()
    for i in range(5):
        browser.offer(f"uav/1/alerts#{i}", f"alert {i}")
    assert browser.take() == ["alert 2", "alert 3", "alert 4"] and browser.dropped == 2


def test_endpoints_come_from_the_telemetry_section() -> None:
    assert dashboard_endpoints(TelemetryConfig(listen=["tcp/0.0.0.0:7447", "tcp/[::]:7448", "tcp/10.0.0.2:7449"])) == [
        "tcp/127.0.0.1:7447", "tcp/[::1]:7448", "tcp/10.0.0.2:7449"]
    assert dashboard_endpoints(TelemetryConfig(dashboard_connect=["tcp/192.168.1.10:7447"])) == ["tcp/192.168.1.10:7447"]
    assert page_url("0.0.0.0", 8080) == "http://127.0.0.1:8080/"
    assert page_url("::1", 80) == "http://[::1]:80/"


def test_serving_beyond_loopback_is_a_warning_that_says_how_to_keep_it_local(tmp_path: Path) -> None:
    config = tmp_path / "ground.yaml"
    config.write_text(yaml.safe_dump({"origin": {"lat": 0.0, "lon": 0.0, "alt": 0.0},
                                      "telemetry": {"listen": [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]}}))
    proc = subprocess.Popen([sys.executable, "-m", "companion.cli", "dashboard", "-c", str(config), "--host", "0.0.0.0",
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        announced = proc.stdout.readline()  # type: ignore[union-attr]
    finally:
        proc.terminate()
        _, stderr = proc.communicate(timeout=10)
    assert "reachable from the network" in announced
    assert "WARNING" in stderr and "not loopback" in stderr and "--host 127.0.0.1" in stderr
