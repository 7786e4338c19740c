"""The real SCIP 2.0 driver (drivers/hokuyo.py) against the emulator (sitl/scip_emulator.py)
over TCP and over a pseudo-terminal, for the UTM-30LX and the URG-04LX; the clock mapping on
synthetic timelines; and a real URG-04LX recording replayed through both."""

from __future__ import annotations

import asyncio
import contextlib
import math
import socket
import subprocess
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

import numpy as np
import pytest

from companion.health import Health, State
from companion.schema import SchemaError, load_text
from drivers import scip
from drivers.base import DeviceLost
from drivers.checks import sensor_driver
from drivers.hokuyo import HokuyoScip, HokuyoSettings, SensorClock, StartupError
from companion.messages import Scan
from sitl.scip_emulator import MODELS, ScipEmulator, cluster_ranges, synthetic_room
from tests.conftest import REPO, free_port

CORRIDOR = Path(__file__).resolve().parents[2] / "shared/data/real/urg04lx-corridor-exp2.dat"
MARK_MM = 1000  # the last step of every synthetic scan carries MARK_MM + its number


def run(body: Callable[[], Awaitable[None]], timeout_s: float = 20.0) -> None:
    asyncio.run(asyncio.wait_for(body(), timeout_s))


async def until(condition: Callable[[], bool], timeout_s: float = 5.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout_s
    while not condition():
        assert asyncio.get_running_loop().time() < deadline, "condition not met in time"
        await asyncio.sleep(0.01)


class Source:
    """Synthetic scans: a room, a few special values, and a scan number in the last step."""

    def __init__(self, params: scip.SensorParams) -> None:
        base = synthetic_room(params)
        # no return, a UTM-30LX error code, just below DMIN, DMIN, DMAX, just above DMAX
        base[10:16] = [0, 3, params.dmin_mm - 1, params.dmin_mm, params.dmax_mm, params.dmax_mm + 1]
        self.base = base
        self.count = 0

    def __call__(self) -> tuple[None, np.ndarray]:
        self.count += 1
        ranges = self.base.copy()
        ranges[-1] = MARK_MM + self.count
        return None, ranges


def mark(scan: Scan) -> int:
    return round(scan.ranges_m[-1] * 1000) - MARK_MM


@contextlib.asynccontextmanager
async def serving(model: str, link: str, **emulator_args: object) -> AsyncIterator[tuple[ScipEmulator, HokuyoSettings]]:
    emulator = ScipEmulator(MODELS[model], Source(MODELS[model]), **emulator_args)  # type: ignore[arg-type]
    if link == "tcp":
        settings = HokuyoSettings(host="127.0.0.1", tcp_port=await emulator.start_tcp(), timeout_s=0.5)
    else:
        settings = HokuyoSettings(port=await emulator.start_pty(), timeout_s=0.5)
    try:
        yield emulator, settings
    finally:
        await emulator.close()


def check_against_emulator(scans: list[Scan], emulator: ScipEmulator) -> None:
    """Ranges, validity and capture times of full-range scans equal what was sent."""
    p = emulator.params
    sent = {int(s.ranges_mm[-1]) - MARK_MM: s for s in emulator.sent if s.fault is None}
    for scan in scans:
        truth = sent[mark(scan)]
        assert np.array_equal(np.rint(scan.ranges_m * 1000).astype(np.int64), truth.ranges_mm)
        assert np.array_equal(scan.valid, (truth.ranges_mm >= p.dmin_mm) & (truth.ranges_mm <= p.dmax_mm))
        assert scan.t_capture == pytest.approx(truth.t_step0 + p.amin * p.step_time_s, abs=3e-3)


# --- streaming ----------------------------------------------------------------------------

@pytest.mark.parametrize("link", ["tcp", "pty"])
@pytest.mark.parametrize(("model", "n"), [("UTM-30LX", 12), ("URG-04LX", 5)])
def test_scans_arrive_as_sent(model: str, n: int, link: str) -> None:
    async def body() -> None:
        async with serving(model, link) as (emulator, settings):
            p = emulator.params
            driver = HokuyoScip(settings, sensor_id="h")
            await driver.open()
            assert driver.params == p
            scans = [await driver.read() for _ in range(n)]
            now = asyncio.get_running_loop().time()
            await driver.close()
            await until(lambda: emulator.commands[-1] == "QT" and not emulator.laser_on)

        check_against_emulator(scans, emulator)
        scan = scans[0]
        assert scan.sensor_id == "h" and scan.ranges_m.size == p.steps
        assert scan.valid[10:16].tolist() == [False, False, False, True, True, False]
        steps = np.arange(p.amin, p.amax + 1)
        assert np.allclose(scan.angles_rad, -(steps - p.afrt) * 2 * np.pi / p.ares)
        assert scan.angles_rad[0] > 0 > scan.angles_rad[-1]  # first step on the right
        assert scan.angles_rad[p.afrt - p.amin] == 0.0
        assert scan.sweep_s == pytest.approx((p.amax - p.amin) * p.step_time_s)
        t = np.array([s.t_capture for s in scans])
        assert np.allclose(np.diff(t), p.scan_period_s, atol=1.5e-3) and t[-1] < now
        assert [s.sequence for s in scans] == list(range(n))

    run(body)


@pytest.mark.parametrize(("mode", "model", "link", "first_commands"), [
    ("scip1", "URG-04LX", "pty", ["QT", "SCIP2.0", "QT", "VV"]),
    ("tm", "UTM-30LX", "tcp", ["QT", "TM2", "QT", "VV"]),
    ("streaming", "UTM-30LX", "tcp", ["QT", "VV"]),
])
def test_start_up_recovery(mode: str, model: str, link: str, first_commands: list[str]) -> None:
    async def body() -> None:
        async with serving(model, link, start_mode=mode) as (emulator, settings):
            driver = HokuyoScip(settings)
            await driver.open()
            scans = [await driver.read() for _ in range(2)]
            await driver.close()
            assert emulator.commands[:len(first_commands)] == first_commands
            md = scip.md_request(MODELS[model].amin, MODELS[model].amax)[:-1].decode()
            bm = emulator.commands.index("BM")
            assert emulator.commands[bm - 1:bm + 2] == ["TM2", "BM", md]
            check_against_emulator(scans, emulator)

    run(body)


def test_steps_cluster_and_min_range() -> None:
    async def body() -> None:
        async with serving("UTM-30LX", "tcp") as (emulator, settings):
            settings.start_step, settings.end_step, settings.cluster, settings.min_range_m = 180, 900, 3, 1.0
            driver = HokuyoScip(settings)
            await driver.open()
            scan = await driver.read()
            await driver.close()
        p = emulator.params
        truth = emulator.sent[0]
        expected = cluster_ranges(truth.ranges_mm[180:901], 3, p.dmin_mm)
        assert scan.ranges_m.size == math.ceil(721 / 3) == expected.size
        assert np.array_equal(np.rint(scan.ranges_m * 1000), expected)
        assert np.array_equal(scan.valid, (expected >= 1000) & (expected <= p.dmax_mm))
        assert np.allclose(scan.angles_rad, p.angle_rad(p.beam_steps(180, 900, 3)))
        assert scan.angles_rad[0] == pytest.approx(math.radians(90 - 0.25))  # centre of steps 180..182
        assert scan.t_capture == pytest.approx(truth.t_step0 + 181 * p.step_time_s, abs=3e-3)

    run(body)


def test_timestamps_unwrap_at_2_24_ms() -> None:
    async def body() -> None:
        async with serving("UTM-30LX", "pty", clock_start_ms=(1 << 24) - 300) as (emulator, settings):
            driver = HokuyoScip(settings)
            await driver.open()
            scans = [await driver.read() for _ in range(30)]
            await driver.close()
        stamps = [s.timestamp_ms for s in emulator.sent]
        assert any(b < a for a, b in zip(stamps, stamps[1:], strict=False)), "the sensor clock did not wrap"
        t = np.array([s.t_capture for s in scans])
        assert np.allclose(np.diff(t), 0.025, atol=1.5e-3)
        check_against_emulator(scans, emulator)

    run(body)


# --- the emulator itself ------------------------------------------------------------------

def test_emulator_answers_like_a_sensor() -> None:
    """The commands the driver does not use (II, GD, MS, RS) and the error statuses."""

    async def body() -> None:
        params = MODELS["URG-04LX"]
        source = Source(params)
        emulator = ScipEmulator(params, source, clock_start_ms=5000)
        reader, writer = await asyncio.open_connection("127.0.0.1", await emulator.start_tcp())

        async def next_reply() -> scip.Reply:
            return scip.split_reply(await asyncio.wait_for(reader.readuntil(b"\n\n"), 1.0))

        async def ask(request: bytes) -> scip.Reply:
            writer.write(request)
            return await next_reply()

        info = scip.parse_info(await ask(scip.II))
        assert info["MODL"] == params.model and info["LASR"] == "OFF"
        assert scip.decode(info["TIME"].encode()) >= 5000
        assert (await ask(scip.gd_request(44, 725))).status == "10"  # laser off
        assert [(await ask(scip.BM)).status for _ in range(2)] == ["00", "02"]
        reply = await ask(scip.gd_request(44, 725, tag="g1"))
        assert reply.echo == b"GD0044072501;g1"
        assert np.array_equal(scip.parse_distance_data(reply).ranges_mm[:-1], source.base[:-1])

        writer.write(scip.md_request(44, 725, scans=2, two_char=True))  # MS, two scans
        replies = [await next_reply() for _ in range(3)]
        assert [r.status for r in replies] == ["00", "99", "99"]
        assert [r.echo[-2:] for r in replies] == [b"02", b"01", b"00"]
        data = scip.parse_distance_data(replies[2])
        assert data.echo.width == 2 and data.ranges_mm.max() == 4095  # 12 bits
        assert np.array_equal(data.ranges_mm[:-1], np.minimum(source.base[:-1], 4095))

        for request, status in [(b"MD0044072601000\n", "04"), (b"MD0100005001000\n", "05"), (b"MD00440725\n", "0C"),
                                (b"MDx044072501000\n", "01"), (b"MD004407250100x\n", "07"), (b"XX\n", "0D"),
                                (scip.SCIP20, "0E"), (b"VV;" + b"x" * 17 + b"\n", "0G"),
                                (scip.tm_request(1), "04"), (scip.tm_request(2), "03"), (b"TM5\n", "01")]:
            assert (await ask(request)).status == status, request
        assert (await ask(scip.RS)).status == "00"  # reset: clock back to 0, laser off
        assert [(await ask(scip.tm_request(0))).status for _ in range(2)] == ["00", "02"]
        assert (await ask(scip.QT)).status == "0E"  # time-adjust mode takes nothing but TM
        assert scip.parse_timestamp_reply(await ask(scip.tm_request(1))) < 1000
        assert (await ask(scip.tm_request(2))).status == "00"
        writer.close()
        await emulator.close()

    run(body)


def test_emulator_cli_serves_a_room() -> None:
    port = free_port(socket.SOCK_STREAM)
    command = [sys.executable, "-m", "sitl.scip_emulator", "--model", "URG-04LX", "--tcp", f"127.0.0.1:{port}"]
    with subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, text=True) as process:
        try:
            assert process.stdout is not None
            assert process.stdout.readline().strip() == f"URG-04LX on tcp 127.0.0.1:{port}"

            async def body() -> None:
                driver = HokuyoScip(HokuyoSettings(host="127.0.0.1", tcp_port=port, model="URG-04LX"))
                await driver.open()
                scan = await driver.read()
                await driver.close()
                assert np.array_equal(np.rint(scan.ranges_m * 1000), synthetic_room(MODELS["URG-04LX"]))

            run(body)
        finally:
            process.terminate()


# --- faults through the frontend -------------------------------------------------------------

class Frontend:
    """drivers.base.SensorDriver around the real backend, recording scans and health changes."""

    def __init__(self, settings: HokuyoSettings) -> None:
        loop = asyncio.get_running_loop()
        self.health = Health(loop.time)
        self.states: list[State] = []
        self.health.on_change(lambda name, new, old: self.states.append(new.state))
        self.scans: list[Scan] = []
        self.driver = sensor_driver("lidar", "h", HokuyoScip(settings), self.health)
        self.driver.subscribe(self.scans.append)
        self.task = asyncio.create_task(self.driver.run())

    async def more_scans(self, n: int) -> None:
        target = len(self.scans) + n
        await until(lambda: len(self.scans) >= target)

    async def stop(self) -> None:
        self.task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await self.task


def test_corrupt_truncated_and_error_replies_are_counted_and_skipped() -> None:
    async def body() -> None:
        async with serving("UTM-30LX", "tcp") as (emulator, settings):
            front = Frontend(settings)
            await front.more_scans(3)
            stats = front.driver.stats
            emulator.corrupt_scans(2)
            emulator.truncate_scans(1)
            await until(lambda: stats.corrupt_frames == 3)
            assert "of 1081 range values" in (stats.last_error or "")  # the truncated one
            emulator.send_status("98")
            await until(lambda: stats.corrupt_frames == 4)
            assert "status 98" in (stats.last_error or "")
            emulator.send_status("21")  # the sensor stops streaming: MD is sent again
            await until(lambda: stats.corrupt_frames == 5)
            assert "streaming restarted" in (stats.last_error or "")
            await front.more_scans(3)
            md = [c for c in emulator.commands if c.startswith("MD")]
            assert len(md) == 2 and stats.reconnects == 0
            emulator.send_status("50")  # hardware trouble: the frontend reopens the device
            await until(lambda: stats.reconnects == 1)
            await front.more_scans(3)
            await front.stop()

        faulty = {int(s.ranges_mm[-1]) - MARK_MM for s in emulator.sent if s.fault in ("corrupt", "truncate")}
        assert len(faulty) == 3
        received = [mark(s) for s in front.scans]
        assert not faulty & set(received)
        assert received == sorted(received)
        # Nothing but the faulty scans was lost while streaming (before the status replies).
        first_status = next(i for i, s in enumerate(emulator.sent) if s.fault and s.fault.startswith("status"))
        before = [int(s.ranges_mm[-1]) - MARK_MM for s in list(emulator.sent)[:first_status] if s.fault is None]
        assert [m for m in received if m <= before[-1]] == before
        # Sequence numbers count the lost scans.
        seq = {mark(s): s.sequence for s in front.scans}
        assert all(seq[b] - seq[a] == b - a for a, b in zip(before, before[1:], strict=False))
        assert front.states[-1] == State.OK and State.LOST in front.states
        check_against_emulator(front.scans, emulator)

    run(body)


@pytest.mark.parametrize(("model", "link", "power_cycle"), [("UTM-30LX", "tcp", False), ("URG-04LX", "pty", True)])
def test_unplug_replug_recovers(model: str, link: str, power_cycle: bool) -> None:
    async def body() -> None:
        async with serving(model, link) as (emulator, settings):
            front = Frontend(settings)
            await front.more_scans(3)
            await emulator.disconnect(0.3, power_cycle=power_cycle)
            await until(lambda: front.driver.stats.reconnects >= 1)
            await front.more_scans(3)
            await front.stop()
        stats = front.driver.stats
        assert stats.reconnects >= 1 and stats.corrupt_frames == 0
        assert front.states[-1] == State.OK and State.LOST in front.states
        component = front.health.get("sensor:h")
        assert component is not None and component.reason.endswith("streaming")
        t = [s.t_capture for s in front.scans]
        assert all(b > a for a, b in zip(t, t[1:], strict=False))
        check_against_emulator(front.scans, emulator)

    run(body)


def test_silent_scanner_is_lost() -> None:
    async def body() -> None:
        params = MODELS["UTM-30LX"]
        room = synthetic_room(params)
        emulator = ScipEmulator(params, [(None, room)] * 3)  # a recording of three scans
        settings = HokuyoSettings(host="127.0.0.1", tcp_port=await emulator.start_tcp(), timeout_s=0.2)
        driver = HokuyoScip(settings)
        try:
            await driver.open()
            for _ in range(3):
                await driver.read()
            with pytest.raises(DeviceLost, match=r"no reply .* \(waiting for the next scan\)"):
                await driver.read()
        finally:
            await driver.close()
            await emulator.close()

    run(body)


def test_start_up_failures_are_os_errors() -> None:
    async def body() -> None:
        async with serving("UTM-30LX", "tcp") as (emulator, settings):
            settings.model = "URG-04LX"
            with pytest.raises(StartupError, match="expected a URG-04LX, found UTM-30LX"):
                await HokuyoScip(settings).open()
            settings.model, settings.end_step = "UTM-30LX", 1081
            with pytest.raises(StartupError, match="outside the scanner's 0..1080"):
                await HokuyoScip(settings).open()
        with pytest.raises(OSError):  # nobody listens any more
            await HokuyoScip(settings).open()
        with pytest.raises(OSError):  # no such device
            await HokuyoScip(HokuyoSettings(port="/nonexistent/ttyACM9")).open()

    run(body)


def test_settings_schema() -> None:
    settings = load_text("{model: UTM-30LX, port: /dev/ttyACM0}", HokuyoSettings)
    assert (settings.port, settings.model, settings.tcp_port, settings.cluster) == ("/dev/ttyACM0", "UTM-30LX", 10940, 1)
    assert load_text("{host: 192.168.0.10}", HokuyoSettings).host == "192.168.0.10"
    for text, key in [("{}", "port"), ("{port: /dev/ttyACM0, host: 1.2.3.4}", "port"),
                      ("{port: /dev/ttyACM0, start_step: 10, end_step: 5}", "end_step"),
                      ("{port: /dev/ttyACM0, cluster: 0}", "cluster")]:
        with pytest.raises(SchemaError) as err:
            load_text(text, HokuyoSettings)
        assert err.value.key_path == key


# --- the clock mapping ----------------------------------------------------------------------

# Both the TM1 reading and each scan timestamp are floored to the millisecond, the TM1 round
# trip adds 0.3 ms here: 3 ms bounds the mapping error (an untracked 500 ppm drift is 300 ms).
CLOCK_ERROR_S = 3e-3


def simulate(drift: float, *, seconds: float = 600.0, period: float = 0.025, delay: float = 0.019,
             start_ms: int = (1 << 24) - 60_000, stall: tuple[float, float] | None = None,
             busy_start_s: float = 0.0, reset_at: float | None = None, seed: int = 0) -> np.ndarray:
    """Errors (s) of SensorClock's host times against the true step-0 times of a scanner whose
    clock runs (1 + drift) fast, with transfer jitter, an optional host stall, a busy start
    (everything 30 ms late) and a clock reset."""
    rng = np.random.default_rng(seed)
    t_true = np.arange(0.0, seconds, period)
    sensor_ms = np.floor(start_ms + t_true * 1000.0 * (1.0 + drift))
    if reset_at is not None:
        after = t_true >= reset_at
        sensor_ms[after] = np.floor((t_true[after] - reset_at) * 1000.0 * (1.0 + drift))
    arrival = t_true + delay + rng.exponential(0.002, t_true.size) + (rng.random(t_true.size) < 0.02) * 0.05
    arrival[t_true < busy_start_s] += 0.030
    if stall is not None:  # the host was busy: everything in the stall arrives at its end
        busy = (arrival > stall[0]) & (arrival < stall[1])
        arrival[busy] = stall[1] + np.arange(busy.sum()) * 1e-4
    tm_host = -0.1  # TM1 answered then, with the sensor clock floored to its millisecond
    clock = SensorClock(math.floor(start_ms + tm_host * 1000.0 * (1.0 + drift)) % (1 << 24), tm_host + 0.0003)
    mapped = np.array([clock.host_time(int(ms) % (1 << 24), a) for ms, a in zip(sensor_ms, arrival, strict=True)])
    return mapped - t_true


@pytest.mark.parametrize("drift", [-500e-6, -100e-6, 0.0, 100e-6, 500e-6])
def test_clock_tracks_drift_across_the_wrap(drift: float) -> None:
    errors = simulate(drift)  # 10 minutes, one wrap; 500 ppm is ten times a crystal's tolerance
    assert np.abs(errors[80:]).max() < CLOCK_ERROR_S  # once the delay floor is learnt (2 s)


def test_clock_ignores_a_busy_start() -> None:
    errors = simulate(100e-6, seconds=60.0, busy_start_s=1.5)  # every scan 30 ms late for 1.5 s
    assert np.abs(errors[80:]).max() < CLOCK_ERROR_S


def test_clock_ignores_a_host_stall() -> None:
    errors = simulate(100e-6, seconds=30.0, stall=(10.0, 10.6))
    assert np.abs(errors[80:]).max() < CLOCK_ERROR_S


def test_clock_reanchors_when_the_sensor_clock_restarts() -> None:
    errors = simulate(100e-6, seconds=30.0, reset_at=12.0)
    assert np.abs(errors[80:]).max() < CLOCK_ERROR_S


# --- a real recording -----------------------------------------------------------------------

def load_corridor() -> tuple[list[int], np.ndarray, np.ndarray]:
    """(timestamps ms, ranges mm (641, 682), wheel ticks (641, 2) left/right) of the recording."""
    if not CORRIDOR.exists():
        pytest.skip(f"real URG-04LX recording not found: {CORRIDOR} (shared data beside the repository)")
    rows = [line.split() for line in CORRIDOR.read_text().splitlines() if line.strip()]
    stamps = [int(r[0]) // 1000 for r in rows]
    ranges = np.array([[int(v) for v in r[24:24 + 682]] for r in rows], dtype=np.int64)
    ticks = np.array([[int(r[2]), int(r[3])] for r in rows], dtype=float)
    return stamps, ranges, ticks


def beam_shift(a: np.ndarray, b: np.ndarray, max_shift: int = 25) -> int:
    """The beam shift s that best maps scan a onto scan b (b[i + s] ~ a[i]), by median error."""
    best = (math.inf, 0)
    for s in range(-max_shift, max_shift + 1):
        x, y = (a[:a.size - s], b[s:]) if s >= 0 else (a[-s:], b[:b.size + s])
        both = (x > 0) & (y > 0)
        if both.sum() >= 30:
            best = min(best, (float(np.median(np.abs(x[both] - y[both]))), s))
    return best[1]


def test_real_urg04lx_recording_through_emulator_and_driver() -> None:
    stamps, ranges, ticks = load_corridor()

    scans: list[Scan] = []

    async def body() -> None:
        # The file's own timestamps, sent 20 times faster than recorded: the clock mapping
        # must keep capture times monotonic even then.
        emulator = ScipEmulator(MODELS["URG-04LX"], zip(stamps, ranges, strict=True), period_s=0.005)
        driver = HokuyoScip(HokuyoSettings(port=await emulator.start_pty(), model="URG-04LX"))
        await driver.open()
        scans.extend([await driver.read() for _ in range(len(stamps))])
        await driver.close()
        await emulator.close()

    run(body, timeout_s=25.0)
    assert len(scans) == 641
    for scan, expected in zip(scans, ranges, strict=True):
        assert np.array_equal(np.rint(scan.ranges_m * 1000).astype(np.int64), expected)
        assert np.array_equal(scan.valid, (expected >= 20) & (expected <= 5600))
    assert not any(s.valid[ranges[i] == 0].any() for i, s in enumerate(scans))
    t = np.array([s.t_capture for s in scans])
    assert np.all(np.diff(t) >= 0)

    # Sweep direction. The recording's README puts beam 341 straight ahead: the driver's
    # angle there is within one step of 0 (PP: AFRT 384 = beam 340), beam 0 is on the right.
    angles = scans[0].angles_rad
    step = 2 * math.pi / 1024
    assert abs(angles[341]) <= step and angles[0] > 0
    # And the wheels agree: when the robot turns left (counter-clockwise seen from above) by
    # d_yaw, a fixed wall's angle in the sensor frame (positive to the right) grows by d_yaw.
    wheel_rad = np.diff(ticks, axis=0) * math.radians(180 / 2000) * 0.077  # metres per wheel
    d_yaw = (wheel_rad[:, 1] - wheel_rad[:, 0]) / (2 * 0.165)
    turning = np.flatnonzero(np.abs(d_yaw) > math.radians(2))
    assert turning.size > 50
    centre = 341
    d_angle = np.array([angles[centre + beam_shift(ranges[k], ranges[k + 1])] - angles[centre] for k in turning])
    assert np.corrcoef(d_angle, d_yaw[turning])[0, 1] > 0.6
    assert np.mean(np.sign(d_angle) == np.sign(d_yaw[turning])) > 0.75
