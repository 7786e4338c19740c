"""Vehicles publishing telemetry from their own zenoh peers (127.0.0.1, scouting off) to a real
`companion dashboard` process, seen through headless Chromium: the fixture of the page tests."""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import yaml

from companion.dashboard.app import spawn_dashboard
from companion.dashboard.headless import HeadlessChromium
from companion.telemetry.publisher import TelemetryPublisher
from companion.telemetry.session import open_session
from tests.conftest import free_port

Publishers = dict[int, TelemetryPublisher]


@contextmanager
def fleet_page(folder: Path, sysids: tuple[int, ...], tick: Callable[[Publishers], None],
               streams: dict[int, tuple[str, ...]] | None = None) -> Iterator[HeadlessChromium]:
    """A browser on the dashboard of vehicles ``sysids``, each on its own zenoh endpoint; ``tick``
    publishes from all of them every 0.1 s; ``streams`` adds pipeline streams to a vehicle's
    publisher, as the daemon does for its pipelines' ``telemetry_streams``."""
    endpoints = {sysid: f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}" for sysid in sysids}
    sessions = [open_session("peer", [endpoints[sysid]], [], False, False) for sysid in sysids]
    publishers = {sysid: TelemetryPublisher(session, sysid) for sysid, session in zip(sysids, sessions)}
    for sysid, names in (streams or {}).items():
        publishers[sysid].add_streams(names)
    config = folder / "ground.yaml"
    config.write_text(yaml.safe_dump({"origin": {"lat": 0.0, "lon": 0.0, "alt": 0.0},
                                      "telemetry": {"dashboard_connect": list(endpoints.values())}}))
    stop = threading.Event()

    def fly() -> None:
        while not stop.wait(0.1):
            tick(publishers)

    flying = threading.Thread(target=fly, daemon=True)
    flying.start()
    dashboard, url = spawn_dashboard(config, 0)
    try:
        with HeadlessChromium() as browser:
            browser.open(url)
            yield browser
    finally:
        dashboard.terminate()
        dashboard.wait(10)
        stop.set()
        flying.join()
        for publisher in publishers.values():
            publisher.close()
        for session in sessions:
            session.close()


def show_vehicle(browser: HeadlessChromium, sysid: int) -> None:
    """Select vehicle ``sysid`` on the page and wait until its pose is on the map (its streams rendered)."""
    browser.wait_for(f"[...document.querySelectorAll('#vehicle-select option')].some((o) => o.value === '{sysid}')",
                     15, f"vehicle {sysid} in the selector")
    browser.evaluate("(() => { const s = document.getElementById('vehicle-select');"
                     f" s.value = '{sysid}'; s.dispatchEvent(new Event('change')); }})()")
    browser.wait_for(f"document.getElementById('vehicle').dataset.north === '{sysid}'", 10, f"vehicle {sysid}'s marker")
