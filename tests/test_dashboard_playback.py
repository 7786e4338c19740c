"""`companion dashboard --play FILE.mcap`: the player's pace, pause, seek and end on an injected
clock; the recording's telemetry read back exactly; the hub's reset; the served events and
playback requests of a real process; and the page in headless Chromium playing a real
lockstep SITL recording."""

from __future__ import annotations

import asyncio
import base64
import http.client
import json
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from companion.dashboard.headless import HeadlessChromium
from companion.dashboard.hub import ALERT_HISTORY, RESET_EVENT, TelemetryHub
from companion.dashboard.playback import PER_SOURCE_ON_SEEK, Player
from companion.dashboard.recorded import RecordedTelemetry, TelemetryMessage
from companion.dashboard.web import DashboardServer
from companion.recording.reader import Recording
from tests.conftest import REPO, free_port
from tests.dashboard_fleet import Publishers, fleet_page
from tests.sitl_helpers import write_sitl_config

RECORDED_S = 10  # the SITL flight recorded for these tests (lockstep: about as long in wall time)


# -- the player, on an injected clock ---------------------------------------------------------

class Clock:
    """A wall clock the test moves (s)."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def message(t: float, stream: str, **payload: object) -> TelemetryMessage:
    data = json.dumps({"v": 1, "t": t, **payload}).encode()
    return TelemetryMessage(t, f"uav/1/{stream}", False, data, -1, 0)


def flight() -> list[TelemetryMessage]:
    """A map and a trajectory published once, poses at 10 Hz for 10 s, the mission at 0 and 5 s,
    alerts at 1, 2 and 3 s; in log-time order."""
    messages = [message(0.0, "map", walls=1), message(0.0, "trajectory", points=3), message(0.0, "mission", step=0)]
    messages += [message(i / 10, "pose", i=i) for i in range(101)]
    messages += [message(5.0, "mission", step=1)] + [message(float(s), "alerts", text=f"alert {s}") for s in (1, 2, 3)]
    return sorted(messages, key=lambda m: m.t)


class Sink:
    """What a player delivered and reset, in order."""

    def __init__(self) -> None:
        self.events: list[TelemetryMessage | str] = []

    def deliver(self, m: TelemetryMessage) -> None:
        self.events.append(m)

    def reset(self) -> None:
        self.events.append("reset")

    def take(self) -> list[TelemetryMessage | str]:
        events, self.events = self.events, []
        return events


def player_of(messages: list[TelemetryMessage]) -> tuple[Player, Sink, Clock]:
    sink, clock = Sink(), Clock()
    return Player(messages, sink.deliver, sink.reset, clock), sink, clock


def names(events: list[TelemetryMessage | str]) -> list[tuple[str, float] | str]:
    return [e if isinstance(e, str) else (e.stream, e.t) for e in events]


def test_messages_are_delivered_when_the_position_reaches_them_at_the_chosen_speed() -> None:
    player, sink, clock = player_of(flight())
    assert player.advance() == 4  # it starts paused at the first instant: only that instant's messages
    clock.now += 5.0
    assert player.advance() == 0 and player.position() == 0.0
    sink.take()
    player.set_speed(2.0)
    player.play()
    clock.now += 1.0  # 2 s of the recording
    player.advance()
    assert player.position() == pytest.approx(2.0)
    assert [e.t for e in sink.take()] == sorted([i / 10 for i in range(1, 21)] + [1.0, 2.0])
    assert player.wait_s() == pytest.approx(0.05)  # the pose at 2.1 s, 0.1 s of recording away at 2x
    player.set_speed(0.25)
    clock.now += 0.2  # 0.05 s of the recording: the next pose is not due yet
    assert player.advance() == 0
    clock.now += 0.25
    player.advance()
    assert names(sink.take()) == [("pose", 2.1)] and player.position() == pytest.approx(2.1125)


def test_a_paused_player_delivers_nothing_and_resumes_where_it_paused() -> None:
    player, sink, clock = player_of(flight())
    player.play()
    clock.now += 3.05
    player.pause()
    assert names(sink.take())[-1] == ("alerts", 3.0)
    clock.now += 100.0
    assert player.advance() == 0 and player.position() == pytest.approx(3.05)
    assert not player.state()["playing"] and player.wait_s() is None
    player.play()
    clock.now += 0.1
    player.advance()
    assert names(sink.take()) == [("pose", 3.1)]


def test_a_seek_resets_then_resends_the_newest_of_every_stream_at_or_before_the_target() -> None:
    player, sink, clock = player_of(flight())
    player.play()
    clock.now += 8.0
    player.advance()
    sink.take()
    player.seek(4.25)  # backwards: the sink's owner must forget the later state
    assert names(sink.take()) == ["reset", ("map", 0.0), ("trajectory", 0.0), ("mission", 0.0),
                                  ("alerts", 1.0), ("alerts", 2.0), ("alerts", 3.0), ("pose", 4.2)]
    assert player.position() == pytest.approx(4.25) and player.playing
    clock.now += 0.8  # on from the target, the mission's step 1 included
    player.advance()
    assert names(sink.take()) == [("pose", 4.3), ("pose", 4.4), ("pose", 4.5), ("pose", 4.6), ("pose", 4.7),
                                  ("pose", 4.8), ("pose", 4.9), ("pose", 5.0), ("mission", 5.0)]
    player.seek(7.0)  # forwards: the same, the mission at 5 s now the newest
    assert names(sink.take()) == ["reset", ("map", 0.0), ("trajectory", 0.0), ("alerts", 1.0), ("alerts", 2.0),
                                  ("alerts", 3.0), ("mission", 5.0), ("pose", 7.0)]
    player.seek(-5.0)  # clamped to the recording's span
    assert names(sink.take()) == ["reset", ("map", 0.0), ("trajectory", 0.0), ("mission", 0.0), ("pose", 0.0)]
    assert player.state()["seeks"] == 3


def test_a_seek_resends_the_recent_alerts_and_every_source_of_a_per_source_stream() -> None:
    alerts = [message(float(i), "alerts", text=str(i)) for i in range(ALERT_HISTORY + 10)]
    checks = [message(i + 0.5, "attitude_check", source=s) for i in range(30) for s in ("gnss", "flow")]
    player, sink, _ = player_of(sorted(alerts + checks, key=lambda m: m.t))
    player.seek(ALERT_HISTORY + 5.0)
    events = sink.take()[1:]
    assert [e.t for e in events if e.stream == "alerts"] == [float(i) for i in range(6, ALERT_HISTORY + 6)]
    sources = [json.loads(e.data)["source"] for e in events if e.stream == "attitude_check"]
    assert len(sources) == PER_SOURCE_ON_SEEK and sources[-2:] == ["gnss", "flow"]


def test_the_player_stops_at_the_end_and_play_starts_it_over() -> None:
    player, sink, clock = player_of(flight())
    player.set_speed(10.0)
    player.play()
    clock.now += 0.9
    player.advance()
    assert player.playing and player.position() == pytest.approx(9.0)
    clock.now += 5.0
    player.advance()
    assert len(sink.take()) == len(flight())
    state = player.state()
    assert not state["playing"] and state["ended"] and state["t"] == 10.0
    clock.now += 5.0
    assert player.advance() == 0 and player.position() == 10.0
    player.play()  # over again from the start
    assert names(sink.take()) == ["reset", ("map", 0.0), ("trajectory", 0.0), ("mission", 0.0), ("pose", 0.0)]
    assert player.playing and player.position() == 0.0


def test_page_requests_play_pause_seek_and_take_only_the_offered_speeds() -> None:
    player, _, clock = player_of(flight())
    assert player.command({"action": "play"})["playing"]
    assert player.command({"action": "speed", "speed": 4})["speed"] == 4.0
    clock.now += 1.0
    assert player.command({"action": "pause"})["t"] == pytest.approx(4.0)
    assert player.command({"action": "seek", "t": 2.5})["t"] == 2.5
    for bad in ({"action": "speed", "speed": 3}, {"action": "speed"}, {"action": "seek"}, {"action": "seek", "t": "1"},
                {"action": "seek", "t": float("nan")}, {"action": "rewind"}, {}):
        with pytest.raises(ValueError):
            player.command(bad)
    assert player.state()["t"] == 2.5 and player.state()["speed"] == 4.0


# -- the hub's reset ----------------------------------------------------------------------------

def test_a_hub_reset_drops_queued_events_tells_every_browser_and_forgets_the_cache() -> None:
    loop = asyncio.new_event_loop()
    try:
        hub = TelemetryHub(loop, clock=lambda: 7.0)
        browser = hub.attach()
        browser.take()
        hub.receive("uav/1/pose", "application/json", b'{"v":1,"t":6.0,"position_ned_m":[1,2,3]}', 6.0)
        hub.receive("uav/1/alerts", "application/json", b'{"v":1,"t":6.5,"text":"x"}', 6.5)
        hub.reset()
        assert browser.take() == [RESET_EVENT]
        hub.receive("uav/1/map", "application/json", b'{"v":1,"t":0.0,"walls_ned_m":[]}', 0.0)
        assert [json.loads(e).get("stream") for e in browser.take()] == ["map"]
        joining = hub.attach()
        events = [json.loads(e) for e in joining.take()]
        assert [e.get("stream", e["type"]) for e in events] == ["status", "map"]
        assert list(events[0]["vehicles"]["1"]["streams"]) == ["map"]  # statistics restarted too
    finally:
        loop.close()


def test_the_live_dashboard_server_takes_no_playback_requests() -> None:
    async def post() -> bytes:
        server = DashboardServer(TelemetryHub(asyncio.get_running_loop()), "127.0.0.1", 0)
        port = await server.start()
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
            body = b'{"action":"pause"}'
            writer.write(b"POST /playback HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                         b"Content-Length: %d\r\n\r\n%s" % (len(body), body))
            answer = await reader.read()
            writer.close()
            return answer
        finally:
            await server.stop()

    assert asyncio.run(post()).startswith(b"HTTP/1.1 405 ")


# -- a real recording -----------------------------------------------------------------------------

@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A part of `companion sitl --mission patrol --lockstep --record DIR` (config/sitl.yaml on
    free ports), RECORDED_S long."""
    directory = tmp_path_factory.mktemp("playback-recording")
    cfg = write_sitl_config(directory / "sitl.yaml", vehicle_port=free_port(), gcs_port=free_port(),
                            zenoh_port=free_port(socket.SOCK_STREAM), mission=None)
    (directory / "missions").symlink_to(REPO / "config" / "missions")
    record = directory / "rec"
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(cfg), "--mission", "patrol",
                           "--lockstep", "--seed", "1", "--seconds", str(RECORDED_S), "--record", str(record)],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return sorted(record.glob("companion-*.mcap"))[0]


def recorded_telemetry(path: Path) -> list[tuple[float, str, object]]:
    """(log time, stream, the JSON document; of a binary stream its encoding and base64 bytes) of
    every telemetry message, read by the recording's reader."""
    out = [(m.t, m.topic.removeprefix("/telemetry/"),
            m.doc if m.schema == "companion.Telemetry" else (m.doc["encoding"], m.doc["base64"]))
           for m in Recording.open(path).messages() if m.topic.startswith("/telemetry/")]
    return sorted(out, key=lambda x: x[0])


def played(recorded: RecordedTelemetry) -> list[tuple[float, str, object]]:
    """The same, as the playback hands them to the hub."""
    out = []
    for m in recorded.messages:
        encoding, payload = recorded.sample(m)
        doc = json.loads(payload) if encoding == "application/json" else (encoding, base64.b64encode(payload).decode())
        out.append((m.t, m.stream, doc))
    return out


def test_the_playback_reads_every_recorded_telemetry_message_exactly(recording: Path) -> None:
    recorded = RecordedTelemetry(recording)
    assert {m.key for m in recorded.messages} >= {"uav/1/pose", "uav/1/map", "uav/1/trajectory", "uav/1/scan",
                                                  "uav/1/mission"}
    assert all(m.data is None for m in recorded.messages)  # a whole part: indexed, its bytes read when played
    assert played(recorded) == recorded_telemetry(recording)
    assert recorded.messages[-1].t - recorded.messages[0].t > RECORDED_S - 1


def test_a_part_cut_by_a_crash_plays_up_to_its_cut(recording: Path, tmp_path: Path) -> None:
    cut = tmp_path / recording.name
    data = recording.read_bytes()
    cut.write_bytes(data[:len(data) * 2 // 3])
    recorded = RecordedTelemetry(cut)
    whole = recorded_telemetry(recording)
    assert 0 < len(recorded.messages) < len(whole)
    assert played(recorded) == recorded_telemetry(cut) == whole[:len(recorded.messages)]


# -- `companion dashboard --play`: the process, then the page --------------------------------------

@pytest.fixture
def playing(recording: Path) -> Iterator[tuple[str, int]]:
    """`companion dashboard --play PART --port 0`: (host, port)."""
    proc = subprocess.Popen([sys.executable, "-m", "companion.cli", "dashboard", "--play", str(recording),
                             "--port", "0"], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    try:
        match = re.search(r"http://(127\.0\.0\.1):(\d+)/", proc.stdout.readline())
        assert match, "companion dashboard --play did not announce its URL"
        yield match[1], int(match[2])
    finally:
        proc.terminate()
        assert proc.wait(10) == 0


def post(address: tuple[str, int], body: object, headers: dict[str, str] | None = None) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection(*address, timeout=5)
    conn.request("POST", "/playback", json.dumps(body), {"Content-Type": "application/json", **(headers or {})})
    response = conn.getresponse()
    answer = response.status, response.read()
    conn.close()
    return answer


def read_events(address: tuple[str, int], until: object, timeout_s: float = 10.0) -> list[dict]:
    """Events of a new GET /events until ``until(events)`` holds."""
    conn = http.client.HTTPConnection(*address, timeout=5)
    conn.request("GET", "/events")
    response = conn.getresponse()
    events: list[dict] = []
    deadline = time.monotonic() + timeout_s
    try:
        while not until(events):  # type: ignore[operator]
            assert time.monotonic() < deadline, [e.get("stream", e["type"]) for e in events]
            line = response.fp.readline()
            if line.startswith(b"data: "):
                events.append(json.loads(line[6:]))
    finally:
        conn.close()
    return events


def test_dashboard_play_serves_the_recording_at_its_times_and_seeks_on_request(
        recording: Path, playing: tuple[str, int]) -> None:
    events = read_events(playing, lambda e: sum(x["type"] == "status" for x in e) >= 3)
    status = [e for e in events if e["type"] == "status"][-1]
    assert "zenoh" not in status and status["playback"]["file"] == recording.name and status["playback"]["playing"]
    samples = [e for e in events if e["type"] == "sample"]
    assert samples and all(e["rx"] == pytest.approx(e["data"]["t"], abs=1e-6) for e in samples)  # recorded times
    assert all(e["rx"] <= status["now"] + 1e-6 for e in samples)  # the hub's clock: the playback position

    start = status["playback"]["start"]
    code, answer = post(playing, {"action": "pause"})
    assert code == 200 and not json.loads(answer)["playing"]
    target = start + 6.0  # after the mission's first goto published its trajectory (at about 5.3 s)
    assert post(playing, {"action": "seek", "t": target})[0] == 200
    joined = read_events(playing, lambda e: sum(x["type"] == "status" for x in e) >= 2)  # the cache, then a status
    assert joined[0]["type"] == "status" and joined[0]["playback"]["t"] == pytest.approx(target)
    rebuilt = {e["stream"]: e["rx"] for e in joined if e["type"] == "sample"}
    assert {"map", "trajectory", "pose", "mission"} <= set(rebuilt) and max(rebuilt.values()) <= target
    assert rebuilt["pose"] == pytest.approx(target, abs=0.1)  # the newest pose before the target, not a later one

    assert post(playing, {"action": "speed", "speed": 3})[0] == 400
    assert post(playing, {"action": "play"}, {"Origin": "http://elsewhere.example"})[0] == 403
    conn = http.client.HTTPConnection(*playing, timeout=5)
    conn.request("POST", "/playback", '{"action": "play"}', {"Content-Type": "text/plain"})  # a form's kind
    assert conn.getresponse().status == 415
    conn.close()


def test_dashboard_play_refuses_a_file_that_is_not_a_recording(tmp_path: Path) -> None:
    (tmp_path / "notes.mcap").write_text("not an MCAP file")
    for path in (tmp_path / "notes.mcap", tmp_path / "missing.mcap"):
        proc = subprocess.run([sys.executable, "-m", "companion.cli", "dashboard", "--play", str(path), "--port", "0"],
                              cwd=REPO, capture_output=True, text=True, timeout=30)
        assert proc.returncode == 2 and "dashboard --play" in proc.stderr and not proc.stdout, proc.stderr


TIME = "Number(document.getElementById('playback-time').dataset.t)"
MARKER = ("(() => { const v = document.getElementById('vehicle'); "
          "return v.dataset.north === undefined ? null : [Number(v.dataset.north), Number(v.dataset.east)]; })()")


def test_the_page_plays_a_recording_and_its_bar_pauses_and_seeks(recording: Path, playing: tuple[str, int]) -> None:
    recorded = RecordedTelemetry(recording)
    poses = [(m.t, json.loads(recorded.sample(m)[1])["position_ned_m"]) for m in recorded.messages if m.stream == "pose"]
    start = recorded.messages[0].t
    with HeadlessChromium() as browser:
        browser.open(f"http://{playing[0]}:{playing[1]}/")
        assert browser.wait_for("!document.getElementById('playback-bar').hidden && "
                                "document.getElementById('playback-time').textContent", 10, "the playback bar")
        browser.wait_for("document.querySelector('#mission-table').textContent.includes('patrol')", 10,
                         "the recorded mission in its panel")
        browser.wait_for(MARKER, 10, "the recorded pose on the map")
        before = browser.evaluate(TIME)
        advanced = browser.wait_for(f"{TIME} >= {before + 0.5} && {TIME}", 5, "the bar's time to advance")
        assert advanced <= start + RECORDED_S + 1

        browser.evaluate("document.getElementById('playback-toggle').click()")
        browser.wait_for("document.getElementById('playback-toggle').textContent === 'play'", 5, "pause")
        paused = browser.evaluate(TIME)
        time.sleep(1.0)
        assert browser.evaluate(TIME) == paused

        for target in (start + 8.0, start + 2.0):  # forwards, then back: the page forgets later poses
            browser.evaluate("(() => { const s = document.getElementById('playback-seek');"
                             f" s.value = '{target}'; s.dispatchEvent(new Event('input'));"
                             " s.dispatchEvent(new Event('change')); })()")
            browser.wait_for(f"Math.abs({TIME} - {target}) < 1e-6", 5, "the bar at the seek's target")
            north, east = next(p for t, p in reversed(poses) if t <= target)[:2]
            assert browser.wait_for(f"(() => {{ const p = {MARKER}; return p && Math.abs(p[0] - {north}) < 1e-9 && "
                                    f"Math.abs(p[1] - {east}) < 1e-9 && p; }})()", 5,
                                    f"the marker at the recorded pose at {target - start:.1f} s")
        assert browser.evaluate("document.getElementById('playback-time').textContent").startswith("2.0 s / ")
        browser.screenshot(REPO / "artifacts" / "dashboard-playback.png")


def test_the_live_page_has_no_playback_bar(tmp_path: Path) -> None:
    def tick(publishers: Publishers) -> None:
        publishers[1].publish("pose", {"position_ned_m": [1.0, 2.0, -1.0], "euler_rad": [0.0, 0.0, 0.0]})

    with fleet_page(tmp_path, (1,), tick) as browser:
        browser.wait_for(MARKER, 15, "the live pose on the map")
        browser.wait_for("document.getElementById('link-badge').dataset.state === 'ok'", 10, "the live link")
        assert browser.evaluate("document.getElementById('playback-bar').hidden") is True
