"""`companion dashboard`: join zenoh as the config's telemetry section says, serve the page.

The dashboard is a zenoh peer (or client, ``telemetry.dashboard_mode``) that listens nowhere
and connects to ``telemetry.dashboard_connect``, or to the daemon's ``listen`` endpoints read
as loopback when that is empty (so ``companion dashboard -c config/sitl.yaml`` joins a running
``companion sitl``). It retries a lost endpoint every second, so a daemon that restarts is
back on the page within about a second of publishing again. It subscribes to every vehicle
(``uav/*/*``) and publishes nothing: there is no command path.

``companion dashboard --play FILE.mcap`` serves the same page from a flight recording instead
(:func:`run_playback`): no zenoh session, the recorded telemetry played into the same hub at
recorded pace, and a playback bar on the page (play, pause, seek, speed).
"""

from __future__ import annotations

import asyncio
import logging
import re
import select
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from companion.config import TelemetryConfig
from companion.dashboard.hub import SUBSCRIPTION, TelemetryHub
from companion.dashboard.web import DashboardServer, is_loopback
from companion.telemetry.session import open_session

if TYPE_CHECKING:  # the live dashboard does not import the recording's modules
    from companion.dashboard.recorded import RecordedTelemetry

log = logging.getLogger("companion.dashboard")

RECONNECT_PERIOD_S = 1.0
STATUS_PERIOD_S = 1.0
CLOSE_TIMEOUT_S = 1.0
READY_TIMEOUT_S = 15.0
PLAYBACK_STATUS_PERIOD_S = 0.25  # the playback bar's position is refreshed this often (wall s)
_WILDCARD = re.compile(r"^(?P<proto>[a-z]+)/(?P<host>0\.0\.0\.0|\[::\])(?=:)")


def dashboard_endpoints(telemetry: TelemetryConfig) -> list[str]:
    """Where the dashboard connects: ``dashboard_connect``, else the ``listen`` endpoints with
    the wildcard addresses 0.0.0.0 and [::] replaced by 127.0.0.1 and [::1]."""
    if telemetry.dashboard_connect:
        return list(telemetry.dashboard_connect)
    loopback = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}
    return [_WILDCARD.sub(lambda m: f"{m['proto']}/{loopback[m['host']]}", e) for e in telemetry.listen]


def page_url(host: str, port: int) -> str:
    """The URL to open for a server bound to ``host``:``port``."""
    if host in ("0.0.0.0", "::", ""):
        host = "127.0.0.1"
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


def spawn_dashboard(config: Path, port: int, timeout_s: float = READY_TIMEOUT_S,
                    extra_args: tuple[str, ...] = ()) -> tuple[subprocess.Popen, str]:
    """Start ``companion dashboard -c CONFIG --port PORT`` (0: any free port) as a process and
    wait until it serves; (the process, the page's URL as it announced it).

    Raises:
        RuntimeError: it exited or announced nothing within ``timeout_s`` (it is then killed).
    """
    proc = subprocess.Popen([sys.executable, "-m", "companion.cli", *extra_args, "dashboard", "-c", str(config),
                             "--port", str(port)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    ready = select.select([proc.stdout], [], [], timeout_s)[0]
    match = re.search(r"http://\S+/", proc.stdout.readline()) if ready else None
    if match is None:
        proc.kill()
        proc.wait()
        raise RuntimeError(f"companion dashboard did not start serving on port {port} within {timeout_s:g} s")
    return proc, match[0]


def run_dashboard(telemetry: TelemetryConfig, host: str, port: int, announce: Callable[[str], None] = print) -> int:
    """Run until SIGINT or SIGTERM; ``announce`` gets the one-line start message with the URL.

    Returns the exit code: 0, or 1 when zenoh or the HTTP port cannot be opened.
    """
    try:
        return asyncio.run(_serve(telemetry, host, port, announce))
    except (zenoh.ZError, OSError) as exc:
        log.error("dashboard: %s", exc)
        return 1


async def _serve(telemetry: TelemetryConfig, host: str, port: int, announce: Callable[[str], None]) -> int:
    loop = asyncio.get_running_loop()
    endpoints = dashboard_endpoints(telemetry)
    mode = telemetry.dashboard_mode
    session = await loop.run_in_executor(None, lambda: open_session(
        mode, [], endpoints, telemetry.multicast_scouting, telemetry.gossip_scouting, RECONNECT_PERIOD_S))
    hub = TelemetryHub(loop)
    subscriber = session.declare_subscriber(SUBSCRIPTION, hub.on_sample)
    server = DashboardServer(hub, host, port)
    try:
        bound = await server.start()
        exposure = "" if is_loopback(host) else " (reachable from the network: read-only)"
        if not is_loopback(host):
            log.warning("dashboard served on %s, not loopback: anyone on that network can watch the telemetry "
                        "(read-only, no authentication); --host 127.0.0.1 keeps it on this machine", host)
        announce(f"companion dashboard: {page_url(host, bound)}{exposure}; zenoh {mode}, connecting to "
                 f"{', '.join(endpoints) or 'nothing'}")
        stop = asyncio.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop.set)
        facts = {"mode": mode, "connect": endpoints}
        while not stop.is_set():
            links = len(list(session.info.peers_zid())) + len(list(session.info.routers_zid()))
            hub.publish_status({"zenoh": {**facts, "links": links}})
            try:
                await asyncio.wait_for(stop.wait(), STATUS_PERIOD_S)
            except TimeoutError:
                pass
    finally:
        await server.stop()
        subscriber.undeclare()
        closer = threading.Thread(target=session.close, daemon=True)  # never hang the exit on zenoh
        closer.start()
        closer.join(CLOSE_TIMEOUT_S)
    return 0


def run_playback(path: Path, host: str, port: int, announce: Callable[[str], None] = print) -> int:
    """Serve the page from the recording ``path`` (any of its parts) until SIGINT or SIGTERM;
    ``announce`` gets the one-line start message with the URL.

    Returns the exit code: 0, 1 when the HTTP port cannot be opened, 2 when the file is not a
    readable recording.
    """
    from companion.dashboard.recorded import RecordedTelemetry
    from companion.recording.reader import RecordingError

    try:
        recorded = RecordedTelemetry(path)
    except (RecordingError, OSError) as exc:
        log.error("dashboard --play: %s", exc)
        return 2
    if not recorded.messages:
        log.error("dashboard --play: %s has no telemetry messages", path)
        return 2
    try:
        return asyncio.run(_serve_playback(recorded, Path(path).name, host, port, announce))
    except RecordingError as exc:  # a chunk that cannot be read, found while playing
        log.error("dashboard --play: %s", exc)
        return 2
    except OSError as exc:
        log.error("dashboard: %s", exc)
        return 1


async def _serve_playback(recorded: RecordedTelemetry, name: str, host: str, port: int,
                          announce: Callable[[str], None]) -> int:
    from companion.dashboard.playback import Player

    loop = asyncio.get_running_loop()
    hub = TelemetryHub(loop, clock=lambda: player.position())  # the hub's clock: the recording's
    player = Player(recorded.messages, deliver=lambda m: hub.receive(m.key, *recorded.sample(m), m.t),
                    reset=hub.reset)
    messages = recorded.messages
    facts = {"file": name, "parts": len(recorded.recording.parts), "messages": len(messages)}
    wake = asyncio.Event()
    stopping = False

    def status() -> None:
        hub.publish_status({"playback": {**facts, **player.state()}})

    def control(request: dict[str, Any]) -> dict[str, Any]:
        player.command(request)
        player.advance()
        status()  # every page's bar moves at once (after a seek, behind the samples it re-sent)
        wake.set()  # the loop's next wait is the new pace's
        return {**facts, **player.state()}

    def stop() -> None:
        nonlocal stopping
        stopping = True
        wake.set()

    server = DashboardServer(hub, host, port, control=control)
    try:
        bound = await server.start()
        if not is_loopback(host):
            log.warning("dashboard served on %s, not loopback: anyone on that network can watch the recording "
                        "and move its playback", host)
        announce(f"companion dashboard: {page_url(host, bound)}; playing {facts['file']} "
                 f"({player.end - player.start:.1f} s, {len(messages)} telemetry messages, {facts['parts']} parts)")
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, stop)
        player.play()
        last_status = -1.0
        while not stopping:
            player.advance()
            if loop.time() - last_status >= PLAYBACK_STATUS_PERIOD_S:
                last_status = loop.time()
                status()
            due = player.wait_s()
            timeout = PLAYBACK_STATUS_PERIOD_S if due is None else min(due, PLAYBACK_STATUS_PERIOD_S)
            wake.clear()
            try:
                await asyncio.wait_for(wake.wait(), timeout)
            except TimeoutError:
                pass
    finally:
        await server.stop()
    return 0
