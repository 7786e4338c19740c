"""The GNSS backends through the sensor frontend: a serial NMEA receiver on a real pty (the test
writes the receiver's side), and the autopilot's GPS_RAW_INT / GPS2_RAW over a real MAVLink link
on loopback UDP (tests/mavlink_peer.py)."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import operator
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from companion import clock, plugins
from companion.config import typed
from companion.health import Health, State
from companion.messages import GNSS_2D, GNSS_3D, GNSS_NO_FIX, GNSS_RTK_FIXED, GnssFix
from drivers.base import SensorDriver
from drivers.checks import KINDS
from drivers.gnss_autopilot import AutopilotGnss, AutopilotGnssSettings
from drivers.gnss_nmea import KNOT_MPS, NmeaGnss, NmeaGnssSettings
from tests.mavlink_peer import FakeAutopilot, make_link, mavlink

LATENCY_S = 0.2  # more than a read can take here: a stamp without it would be too late
EPOCH_S = 0.1  # a 10 Hz receiver


def sentence(body: str, checksum: int | None = None) -> bytes:
    """``$body*HH\\r\\n`` with the right checksum (or ``checksum`` instead, to corrupt it)."""
    good = functools.reduce(operator.xor, body.encode(), 0)
    return f"${body}*{good if checksum is None else checksum:02X}\r\n".encode()


def epoch(i: int, *, bad: str | None = None, without: str | None = None) -> list[bytes]:
    """One epoch as a u-blox receiver sends it (RMC, VTG, GGA, GSA, GSV, GST), at 12:35:19 + i/10 s
    UTC, latitude 48 deg 07.038 + i/1000 min N (so a fix tells its epoch), 22.4 kn at 84.4 deg;
    the sentence type ``bad`` with a wrong checksum, the type ``without`` left out."""
    utc = f"1235{19 + i // 10:02d}.{i % 10}0"
    lat = f"4807.{38 + i:03d}"
    bodies = [
        f"GNRMC,{utc},A,{lat},N,01131.000,E,022.4,084.4,230394,003.1,W,A",
        "GNVTG,084.4,T,,M,022.4,N,041.5,K,A",
        f"GNGGA,{utc},{lat},N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,",
        "GNGSA,A,3,04,05,,09,12,,,24,,,,,2.5,1.3,2.1",
        "GPGSV,2,1,08,01,40,083,46,02,17,308,41,12,07,344,39,14,22,228,45",
        f"GNGST,{utc},0.006,0.023,0.020,273.6,0.3,0.4,0.5",
    ]
    return [sentence(b, 0 if b[2:5] == bad else None) for b in bodies if b[2:5] != without]


def lat_of(i: int) -> float:
    return 48.0 + (7.038 + i / 1000.0) / 60.0


class Pty:
    """The receiver's end of a pseudo-terminal; ``path`` (a symlink) names the port the backend opens,
    so that a new pty can take the old one's place as a replugged receiver would."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.master, self._slave = os.openpty()
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
        path.symlink_to(os.ttyname(self._slave))

    def write(self, lines: list[bytes]) -> None:
        os.write(self.master, b"".join(lines))

    def close(self) -> None:
        for fd in (self.master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.fixture
def pty(tmp_path: Path) -> Iterator[Pty]:
    p = Pty(tmp_path / "gps")
    yield p
    p.close()


def frontend(backend: Any) -> tuple[SensorDriver, Health, list[GnssFix]]:
    health = Health(clock.now)
    kind = KINDS["gnss"]
    driver = SensorDriver("gps", backend, health, kind.check, kind.stamp)
    fixes: list[GnssFix] = []
    driver.subscribe(fixes.append)
    return driver, health, fixes


async def until(condition: Callable[[], Any], what: str, timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"timed out after {timeout_s:g} s waiting for {what}"
        await asyncio.sleep(0.01)


def state(health: Health) -> State | None:
    component = health.get("sensor:gps")
    return None if component is None else component.state


async def streaming(driver: SensorDriver, health: Health) -> asyncio.Task:
    """Run the frontend until its port is open."""
    task = asyncio.create_task(driver.run())
    await until(lambda: state(health) == State.OK, "the port to open")
    return task


async def stop(task: asyncio.Future) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def nmea(pty: Pty, timeout_s: float = 1.0) -> NmeaGnss:
    return NmeaGnss(NmeaGnssSettings(port=str(pty.path), baud=115200, latency_s=LATENCY_S, timeout_s=timeout_s), "gps")


# --- NMEA --------------------------------------------------------------------------------------

def test_each_nmea_epoch_becomes_one_fix_with_position_velocity_accuracy_and_capture_time(pty: Pty) -> None:
    """The first epoch is handed out when the second begins; the later ones as soon as their last
    sentence (GST) arrives, without waiting for the next epoch."""
    async def main() -> tuple[list[GnssFix], list[float], SensorDriver]:
        driver, health, fixes = frontend(nmea(pty))
        task = await streaming(driver, health)
        written = []
        for i in range(4):
            written.append(clock.now())
            pty.write(epoch(i))
            await until(lambda: len(fixes) >= i, f"the fix of epoch {i - 1}")
            await asyncio.sleep(EPOCH_S)
        await until(lambda: len(fixes) == 4, "the last epoch's fix")
        await stop(task)
        return fixes, written, driver

    fixes, written, driver = asyncio.run(main())
    assert driver.stats.corrupt_frames == 0 and driver.stats.rejected == {}
    assert [f.lat_deg for f in fixes] == pytest.approx([lat_of(i) for i in range(4)], abs=1e-9)
    fix = fixes[-1]
    assert fix.receiver_id == "gps" and fix.fix_type == GNSS_3D and fix.satellites == 8
    assert fix.lon_deg == pytest.approx(11.0 + 31.0 / 60.0) and fix.alt_m == pytest.approx(545.4)
    speed, course = 22.4 * KNOT_MPS, math.radians(84.4)
    np.testing.assert_allclose(fix.velocity_ned_mps, [speed * math.cos(course), speed * math.sin(course), math.nan])
    assert fix.h_acc_m == pytest.approx(0.5) and fix.v_acc_m == pytest.approx(0.5)  # hypot(0.3, 0.4); 0.5
    assert fix.speed_acc_mps is None and not fix.jamming
    for f, t_written in zip(fixes, written):  # first byte's arrival, less the receiver's latency
        assert t_written - LATENCY_S <= f.t_capture < t_written - LATENCY_S + 0.1


def test_nmea_sentences_with_bad_checksums_or_garbage_are_counted_and_skipped(pty: Pty) -> None:
    """Epoch 2 loses its GST (its fix comes without accuracy, one epoch late; epoch 3 is still awaited
    whole), epoch 4 its GGA (no fix); a garbage line and a sentence without ``$`` come between
    epochs. Every other epoch still gives its fix."""
    async def main() -> tuple[list[GnssFix], SensorDriver]:
        driver, health, fixes = frontend(nmea(pty))
        task = await streaming(driver, health)
        for i in range(1, 7):
            pty.write(epoch(i, bad={2: "GST", 4: "GGA"}.get(i)) + [b"\x00\x17\xffgarbage\r\n", b"GPTXT,01,01,02,ANT*00\r\n"])
            await asyncio.sleep(EPOCH_S)
        await until(lambda: len(fixes) == 5, "the fixes of the good epochs")
        await asyncio.sleep(EPOCH_S)
        await stop(task)
        return fixes, driver

    fixes, driver = asyncio.run(main())
    assert driver.stats.corrupt_frames == 2 + 2 * 6
    assert [f.lat_deg for f in fixes] == pytest.approx([lat_of(i) for i in (1, 2, 3, 5, 6)], abs=1e-9)
    assert fixes[1].h_acc_m is None and fixes[1].fix_type == GNSS_3D
    assert all(f.h_acc_m == pytest.approx(0.5) for f in fixes if f is not fixes[1])


def test_a_receiver_that_stops_sending_a_sentence_type_is_handed_out_without_delay_again(pty: Pty) -> None:
    """GST stops after epoch 1: epochs 2 and 3 come one epoch late (each ended by the next one's
    start), then the sentence types are learnt again and epochs 4 and 5 come at once."""
    async def main() -> list[GnssFix]:
        driver, health, fixes = frontend(nmea(pty))
        task = await streaming(driver, health)
        for i in range(6):
            pty.write(epoch(i, without=None if i < 2 else "GST"))
            await asyncio.sleep(0.02)
        await until(lambda: len(fixes) == 6, "the fix of epoch 5 without an epoch 6")
        await stop(task)
        return fixes

    fixes = asyncio.run(main())
    assert [f.lat_deg for f in fixes] == pytest.approx([lat_of(i) for i in range(6)], abs=1e-9)
    assert [f.h_acc_m is None for f in fixes] == [False, False, True, True, True, True]


def test_nmea_fix_types_from_gga_quality_and_gsa_mode_and_a_receiver_without_time(pty: Pty) -> None:
    """RTK fixed (quality 4); GSA mode 2 lowers a fix to 2-D (no velocity then); quality 0 is no fix;
    a GGA with no time (a receiver still searching) is a no-fix report on its own."""
    def gga(utc: str, quality: int) -> bytes:
        return sentence(f"GPGGA,{utc},4807.038,S,01131.000,W,{quality},12,0.9,545.4,M,46.9,M,1.0,0000")

    rmc = sentence("GPRMC,123520.00,A,4807.038,S,01131.000,W,001.0,180.0,230394,,,A")

    async def main() -> list[GnssFix]:
        driver, health, fixes = frontend(nmea(pty))
        task = await streaming(driver, health)
        for lines in ([sentence("GPGGA,,,,,,0,00,99.99,,,,,,")],
                      [gga("123519.00", 4), sentence("GPGSA,A,3,01,02,03,04,,,,,,,,,1.0,0.9,0.8")],
                      [gga("123520.00", 1), rmc, sentence("GPGSA,A,2,01,02,03,,,,,,,,,,1.0,0.9,0.8")],
                      [sentence("GPGGA,123521.00,,,,,0,03,,,M,,M,,"), sentence("GPGSA,A,1,,,,,,,,,,,,,,,")]):
            pty.write(lines)
            await asyncio.sleep(EPOCH_S)
        await until(lambda: len(fixes) == 4, "four fixes")
        await stop(task)
        return fixes

    no_time, rtk, two_d, no_fix = asyncio.run(main())
    assert no_time.fix_type == GNSS_NO_FIX and no_time.satellites == 0
    assert rtk.fix_type == GNSS_RTK_FIXED and rtk.lat_deg == pytest.approx(-(48.0 + 7.038 / 60.0))
    assert rtk.lon_deg == pytest.approx(-(11.0 + 31.0 / 60.0))
    assert two_d.fix_type == GNSS_2D and two_d.velocity_ned_mps is None
    assert no_fix.fix_type == GNSS_NO_FIX and not no_fix.has_position and no_fix.satellites == 3


def test_an_unplugged_nmea_receiver_is_reported_lost_and_found_again_when_replugged(pty: Pty, tmp_path: Path) -> None:
    async def main() -> tuple[list[GnssFix], SensorDriver, str]:
        driver, health, fixes = frontend(nmea(pty))
        task = await streaming(driver, health)
        pty.write(epoch(0) + epoch(1))
        await until(lambda: len(fixes) == 1, "the first fix")
        pty.close()  # unplugged
        await until(lambda: state(health) == State.LOST, "the loss to be reported")
        reason = health.get("sensor:gps").reason
        replugged = Pty(pty.path)
        try:
            await until(lambda: state(health) == State.OK, "the port to be reopened")
            replugged.write(epoch(5) + epoch(6))
            await until(lambda: len(fixes) == 2, "a fix from the replugged receiver")
        finally:
            replugged.close()
        await stop(task)
        return fixes, driver, reason

    fixes, driver, reason = asyncio.run(main())
    assert reason.startswith(f"NMEA receiver on {pty.path} lost") and driver.stats.reconnects == 1
    assert fixes[1].lat_deg == pytest.approx(lat_of(5), abs=1e-9)


def test_an_nmea_receiver_sending_nothing_decodable_is_lost_after_the_timeout(pty: Pty) -> None:
    """A wrong baud rate looks like this: every line corrupt, no fix."""
    async def main() -> tuple[SensorDriver, str]:
        driver, health, _ = frontend(nmea(pty, timeout_s=0.5))
        task = await streaming(driver, health)
        for _ in range(3):
            pty.write([b"\xf8\x1e\x80~\x06\xe0\r\n"])
            await asyncio.sleep(0.05)
        await until(lambda: state(health) == State.LOST, "the timeout")
        reason = health.get("sensor:gps").reason
        await stop(task)
        return driver, reason

    driver, reason = asyncio.run(main())
    assert driver.stats.corrupt_frames == 3 and "no fix (GGA) for 0.5 s" in reason


def test_a_missing_nmea_port_cannot_be_opened() -> None:
    async def main() -> str:
        backend = NmeaGnss(NmeaGnssSettings(port="/nonexistent/ttyGPS"), "gps")
        with pytest.raises(OSError) as raised:
            await backend.open()
        return str(raised.value)

    assert "/nonexistent/ttyGPS" in asyncio.run(main())


# --- autopilot -------------------------------------------------------------------------------

def gps_raw_int(time_usec: int, fix_type: int = 3, *, vel: int = 500, cog: int = 9000, satellites: int = 14,
                h_acc: int = 1200, v_acc: int = 2500, vel_acc: int = 300) -> mavlink.MAVLink_message:
    """1.2966 N 103.7764 E, 10.5 m AMSL, 5 m/s towards the east (cog 90 deg)."""
    return mavlink.MAVLink_gps_raw_int_message(time_usec, fix_type, 12966000, 1037764000, 10500, 90, 150, vel, cog,
                                               satellites, 10200, h_acc, v_acc, vel_acc, 0, 0)


async def linked(instance: int = 1, timeout_s: float = 1.0) -> tuple[FakeAutopilot, asyncio.Future, SensorDriver,
                                                                     Health, list[GnssFix]]:
    """A link connected to a fake autopilot, and the autopilot GNSS backend's frontend running on it."""
    autopilot = FakeAutopilot()
    link = make_link(autopilot.url)
    link_task = asyncio.create_task(link.run())
    await autopilot.connect(link)
    backend = AutopilotGnss(link, AutopilotGnssSettings(instance=instance, latency_s=LATENCY_S, timeout_s=timeout_s),
                            "gps")
    driver, health, fixes = frontend(backend)
    driver_task = await streaming(driver, health)
    return autopilot, asyncio.gather(link_task, driver_task), driver, health, fixes


def test_gps_raw_int_becomes_a_fix_in_degrees_metres_and_ned_velocity() -> None:
    async def main() -> tuple[list[GnssFix], float]:
        autopilot, tasks, _, _, fixes = await linked()
        sent_at = clock.now()
        autopilot.send(gps_raw_int(1_000_000))
        await autopilot.until(lambda: fixes, "the fix")
        await stop(tasks)
        autopilot.close()
        return fixes, sent_at

    fixes, sent_at = asyncio.run(main())
    fix = fixes[0]
    assert fix.fix_type == GNSS_3D and fix.satellites == 14 and not fix.jamming
    assert fix.lat_deg == pytest.approx(1.2966) and fix.lon_deg == pytest.approx(103.7764)
    assert fix.alt_m == pytest.approx(10.5)
    np.testing.assert_allclose(fix.velocity_ned_mps, [0.0, 5.0, math.nan], atol=1e-12)
    assert (fix.h_acc_m, fix.v_acc_m, fix.speed_acc_mps) == pytest.approx((1.2, 2.5, 0.3))
    assert sent_at - LATENCY_S <= fix.t_capture < sent_at - LATENCY_S + 0.1  # arrival less the latency


def test_unknown_gps_raw_int_values_are_none_and_a_repeated_solution_is_skipped() -> None:
    """satellites 255, accuracies 0 (not reported), cog UINT16_MAX: unknown; a 2-D fix has no
    velocity; a fix repeating the previous time_usec is the same solution and is skipped, but
    a no-fix report with it (ArduPilot: the time of its last fix) is not."""
    async def main() -> list[GnssFix]:
        autopilot, tasks, _, _, fixes = await linked()
        autopilot.send(gps_raw_int(1_000_000, satellites=255, h_acc=0, v_acc=0, vel_acc=0, cog=0xFFFF))
        autopilot.send(gps_raw_int(1_000_000))  # the same solution again
        autopilot.send(gps_raw_int(1_200_000, fix_type=2))
        autopilot.send(gps_raw_int(1_200_000, fix_type=1))  # the fix lost
        await autopilot.until(lambda: len(fixes) == 3, "three fixes")
        await asyncio.sleep(0.1)
        await stop(tasks)
        autopilot.close()
        return fixes

    unknown, two_d, no_fix = asyncio.run(main())
    assert unknown.satellites is None and unknown.velocity_ned_mps is None
    assert (unknown.h_acc_m, unknown.v_acc_m, unknown.speed_acc_mps) == (None, None, None)
    assert two_d.fix_type == GNSS_2D and two_d.velocity_ned_mps is None and two_d.h_acc_m == pytest.approx(1.2)
    assert no_fix.fix_type == GNSS_NO_FIX and not no_fix.has_position


def test_the_second_receiver_is_read_from_gps2_raw_only() -> None:
    async def main() -> list[GnssFix]:
        autopilot, tasks, _, _, fixes = await linked(instance=2)
        autopilot.send(gps_raw_int(1_000_000))
        autopilot.send(mavlink.MAVLink_gps2_raw_message(2_000_000, 6, -337000000, 1512000000, 25000, 70, 120, 30, 18000,
                                                        20, 3, 1000, 0, 25100, 20, 40, 50, 0))
        await autopilot.until(lambda: fixes, "the fix")
        await asyncio.sleep(0.1)
        await stop(tasks)
        autopilot.close()
        return fixes

    [fix] = asyncio.run(main())
    assert fix.fix_type == 6 and fix.lat_deg == pytest.approx(-33.7) and fix.lon_deg == pytest.approx(151.2)
    assert fix.alt_m == pytest.approx(25.0) and fix.satellites == 20
    np.testing.assert_allclose(fix.velocity_ned_mps, [-0.3, 0.0, math.nan], atol=1e-12)  # 0.3 m/s due south
    assert (fix.h_acc_m, fix.v_acc_m, fix.speed_acc_mps) == pytest.approx((0.02, 0.04, 0.05))


def test_the_autopilot_receiver_is_lost_without_messages_and_back_when_they_return() -> None:
    async def main() -> tuple[list[GnssFix], SensorDriver, str]:
        autopilot, tasks, driver, health, fixes = await linked(timeout_s=0.3)
        autopilot.send(gps_raw_int(1_000_000))
        await autopilot.until(lambda: state(health) == State.LOST, "the loss")
        reason = health.get("sensor:gps").reason
        await autopilot.until(lambda: state(health) == State.OK, "the reopening")
        autopilot.send(gps_raw_int(2_000_000))
        await autopilot.until(lambda: len(fixes) == 2, "a fix after the loss")
        await stop(tasks)
        autopilot.close()
        return fixes, driver, reason

    fixes, driver, reason = asyncio.run(main())
    assert "no GPS_RAW_INT for 0.3 s" in reason and driver.stats.reconnects == 1


def test_a_receiver_that_never_sends_is_reported_lost_but_is_no_reconnect() -> None:
    """Before the autopilot streams (link up, streams not yet asked) the sensor says lost, honestly,
    but a reconnect counts only a loss after data flowed."""
    async def main() -> tuple[SensorDriver, str, int]:
        autopilot, tasks, driver, health, _ = await linked(timeout_s=0.2)
        await autopilot.until(lambda: state(health) == State.LOST, "the loss")
        reason = health.get("sensor:gps").reason
        await asyncio.sleep(0.6)  # reopened and timed out again
        await stop(tasks)
        autopilot.close()
        return driver, reason, driver._attempts

    driver, reason, attempts = asyncio.run(main())
    assert "no GPS_RAW_INT for 0.2 s" in reason and attempts >= 2
    assert driver.stats.reconnects == 0


def test_both_backends_are_registered_with_settings_typed_from_the_config() -> None:
    nmea_entry, autopilot_entry = plugins.backend("gnss", "nmea"), plugins.backend("gnss", "autopilot")
    assert nmea_entry is not None and autopilot_entry is not None
    settings = typed({"port": "/dev/ttyUSB0", "baud": 38400, "latency_s": 0.1}, nmea_entry.settings)
    assert settings == NmeaGnssSettings(port="/dev/ttyUSB0", baud=38400, latency_s=0.1)
    assert typed({"instance": 2}, autopilot_entry.settings) == AutopilotGnssSettings(instance=2)
