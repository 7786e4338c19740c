"""MAVLink 2 signing end to end (companion/mavlink/signing.py), over real MAVLink on loopback:

- the daemon's link with a key takes only correctly signed messages: unsigned, wrong-key,
  replayed and forged-timestamp frames are dropped and counted, never as parse errors;
- the built-in vehicle with ``--signing-key`` and the daemon with the same key fly together
  (in-process and through ``companion sitl``), and what a ground station injects unsigned is
  refused by the daemon; an unsigned daemon cannot command the signing vehicle;
- real ArduCopter 4.0.5 SITL (skipped without the binary): signing set up with SETUP_SIGNING on a
  MAVLink 2 port, the signed link works, an unsigned client's command is refused.
"""

from __future__ import annotations

import asyncio
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import yaml

from companion.config import load_config
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import Commander
from companion.mavlink.link import MavlinkLink, mavlink
from companion.mavlink.signing import signing_timestamp
from sitl.ardupilot import ArduPilotSitl, SitlOptions, default_defaults
from tests.ardupilot_helpers import ARDUCOPTER, requires_ardupilot
from tests.conftest import REPO, free_port
from tests.mavlink_peer import FakeAutopilot, make_link
from tests.sitl_helpers import (GroundStation, PipelineDaemon, Processes, TruthPipeline, read_log,
                                run_daemon_with_vehicle, vehicle_args, write_config, write_sitl_config)

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
ONE_HOUR_10US = 3600 * 100_000


def key_file(directory: Path, key: bytes = KEY) -> Path:
    """The key as the README says to make one (32 raw bytes)."""
    path = directory / "mavlink.key"
    path.write_bytes(key)
    return path


def packer(key: bytes | None, link_id: int = 0, timestamp: int | None = None) -> mavlink.MAVLink:
    """A codec speaking as the autopilot (1, 1) that packs frames: unsigned, or signed with ``key``."""
    codec = mavlink.MAVLink(None, 1, 1)
    if key is not None:
        codec.signing.secret_key = key
        codec.signing.sign_outgoing = True
        codec.signing.link_id = link_id
        codec.signing.timestamp = signing_timestamp(time.time()) if timestamp is None else timestamp
    return codec


def attitude(boot_ms: int) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


# -- the daemon's link -----------------------------------------------------------------------


def test_the_signed_link_takes_signed_messages_and_drops_and_counts_the_others() -> None:
    fake = FakeAutopilot(key=KEY)
    seen: list[int] = []

    async def main() -> MavlinkLink:
        link = make_link(fake.url, key=KEY)
        link.subscribe("ATTITUDE", lambda msg: seen.append(msg.time_boot_ms))
        task = asyncio.ensure_future(link.run())
        try:
            await fake.connect(link)  # signed both ways
            fake.attitude(1000)
            fake.write(attitude(1010).pack(packer(None)))  # unsigned
            fake.write(attitude(1020).pack(packer(OTHER_KEY)))  # another key
            genuine = attitude(1030).pack(fake.conn.mav)
            fake.write(genuine)
            fake.write(genuine)  # replayed: its timestamp is not newer
            stream = fake.conn.mav.signing.link_id  # a forged frame on the fake's own stream, an hour ahead
            fake.write(attitude(1040).pack(packer(OTHER_KEY, stream, signing_timestamp(time.time()) + ONE_HOUR_10US)))
            fake.attitude(1050)  # the genuine stream is not locked out by the forged timestamp
            await fake.until(lambda: 1050 in seen, "the last genuine ATTITUDE")
            return link
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        link = asyncio.run(main())
    finally:
        fake.close()
    assert seen == [1000, 1030, 1050]
    assert link.stats.unsigned_rejected == 1
    assert link.stats.bad_signatures == 3  # the other key, the replay, the forged timestamp
    assert link.stats.parse_errors == 0
    assert not [m for m in fake.received if m.get_type() == "BAD_DATA"]  # everything the link sent was signed
    assert all(m.get_signed() for m in fake.received)


# -- the built-in vehicle --------------------------------------------------------------------


def inject_unsigned_heartbeats(gcs: GroundStation, count: int, stop: threading.Event) -> None:
    """A ground station on a vehicle GCS link sends ``count`` unsigned HEARTBEATs, which the vehicle
    forwards to the companion as they came (once it knows the companion: its HEARTBEAT was forwarded here)."""
    gcs.wait_for(lambda m: m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 197, 30, "the companion")
    for _ in range(count):
        if stop.is_set():
            return
        gcs.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        gcs.pump(0.1)


def test_the_signing_vehicle_and_daemon_fly_on_the_estimate_and_unsigned_injections_are_refused(
        tmp_path: Path, procs: Processes) -> None:
    port = free_port()
    cfg = load_config(write_config(tmp_path / "companion.yaml", vehicle_port=port, mission=False, sim_state_hz=50,
                                   mavlink={"signing_key_file": str(key_file(tmp_path))}))
    gcs = GroundStation()
    log = tmp_path / "flight-log.json"
    args = vehicle_args(port, log=log, lockstep=True, seconds=8.0, position_source="extnav", gps=False,
                        gcs=(gcs.url_for_vehicle,))
    vehicle = procs.start("vehicle", [*args, "--signing-key", str(tmp_path / "mavlink.key")])
    stop = threading.Event()
    injector = threading.Thread(target=inject_unsigned_heartbeats, args=(gcs, 5, stop), daemon=True)
    injector.start()
    daemon = PipelineDaemon(cfg, lambda truth: TruthPipeline(truth, 1))
    try:
        assert run_daemon_with_vehicle(daemon, vehicle) == 0
    finally:
        stop.set()
        injector.join(timeout=5)
        gcs.close()
    assert vehicle.returncode == 0, procs.output("vehicle")
    flight = read_log(log)
    assert flight["signing"] == {"unsigned_rejected": 0, "bad_signatures": 0}
    assert flight["external_nav"]["first_in_use_at"] is not None  # the daemon's estimate reached the autopilot
    assert len(flight["vision_position"]["t_rx"]) > 100
    assert daemon.state.firmware is not None and daemon.state.firmware.version is not None
    assert daemon.link.stats.unsigned_rejected == 5  # the ground station's, forwarded by the vehicle
    assert daemon.link.stats.bad_signatures == 0 and daemon.link.stats.parse_errors == 0


def test_companion_sitl_with_a_key_runs_the_vehicle_signed(tmp_path: Path) -> None:
    """`companion sitl` hands the daemon's mavlink.signing_key_file to the built-in vehicle."""
    config = write_sitl_config(tmp_path / "companion.yaml", vehicle_port=free_port(), gcs_port=free_port(),
                               zenoh_port=free_port(socket.SOCK_STREAM), mission=None)
    raw = yaml.safe_load(config.read_text())
    raw["mavlink"]["signing_key_file"] = "mavlink.key"  # beside the config
    config.write_text(yaml.safe_dump(raw, sort_keys=False))
    key_file(tmp_path)
    report_path = tmp_path / "report.json"
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(config), "--lockstep",
                           "--seconds", "8", "--report", str(report_path)],
                          cwd=REPO, capture_output=True, text=True, timeout=90)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    found = re.search(r"flight log \(truth, everything the autopilot received\) in (\S+)", proc.stdout)
    assert found is not None, proc.stdout[-2000:]
    flight = read_log(Path(found.group(1)))
    assert flight["signing"] == {"unsigned_rejected": 0, "bad_signatures": 0}
    assert flight["origin"]["set_at"] is not None
    assert len(flight["vision_position"]["t_rx"]) > 30  # the lidar estimate, signed, reached the vehicle


def test_an_unsigned_daemon_cannot_command_the_signing_vehicle(tmp_path: Path, procs: Processes) -> None:
    port = free_port()
    cfg = write_config(tmp_path / "companion.yaml", vehicle_port=port, mission=False)
    log = tmp_path / "flight-log.json"
    vehicle = procs.start("vehicle", [*vehicle_args(port, log=log, seconds=6.0),
                                      "--signing-key", str(key_file(tmp_path))])
    daemon = procs.start("daemon", [sys.executable, "-m", "companion.cli", "run", "-c", str(cfg)])
    assert vehicle.wait(30) == 0, procs.output("vehicle")
    Processes.stop(daemon)
    flight = read_log(log)
    assert flight["commands"] == []  # not one COMMAND_LONG taken: no stream, no mode, no arming
    assert flight["origin"]["set_at"] is None  # SET_GPS_GLOBAL_ORIGIN refused too
    assert flight["signing"]["unsigned_rejected"] > 5 and flight["signing"]["bad_signatures"] == 0
    assert "does the companion sign with the same key" in procs.output("vehicle")


# -- real ArduPilot --------------------------------------------------------------------------


def ardupilot_with_mavlink2_on_serial1(tmp_path: Path) -> ArduPilotSitl:
    """ArduCopter SITL with SERIAL1 on MAVLink 2 (signing needs it; 4.0 defaults to MAVLink 1 there)."""
    defaults = tmp_path / "defaults.parm"
    defaults.write_text(default_defaults(ARDUCOPTER).read_text() + "\nSERIAL1_PROTOCOL 2\n")
    sitl = ArduPilotSitl(SitlOptions(ARDUCOPTER, defaults=defaults, home=(1.2966, 103.7764, 10.0, 0.0)),
                         tmp_path / "sitl")
    sitl.start(wipe=True)
    assert sitl.wait_listening(30), sitl.output.read_text()[-2000:]
    return sitl


def acked(conn, command: int, seconds: float) -> bool:  # type: ignore[no-untyped-def]
    """Send COMMAND_LONG ``command`` (with HEARTBEATs, so ArduPilot talks) and whether an ACK came."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        conn.mav.command_long_send(1, 1, command, 0, 1, 0, 0, 0, 0, 0, 0)
        if conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=0.5) is not None:
            return True
    return False


@requires_ardupilot
def test_ardupilot_4_0_signing_set_up_over_mavlink_takes_the_signed_link_and_refuses_unsigned(
        tmp_path: Path) -> None:
    """What ArduCopter 4.0.5 does (checked here): it takes SETUP_SIGNING from any MAVLink 2 port, even
    unsigned while it has no key; from then on it refuses unsigned messages on every port but
    SERIAL0 (its "USB" port, always trusted), and signs what it sends once the peer signs."""
    from pymavlink import mavutil

    sitl = ardupilot_with_mavlink2_on_serial1(tmp_path)
    try:
        gcs = mavutil.mavlink_connection(sitl.url(1), source_system=255, source_component=190)
        assert acked(gcs, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 10)  # unsigned works before
        gcs.mav.setup_signing_send(1, 1, KEY, signing_timestamp(time.time()))
        time.sleep(1.0)
        assert not acked(gcs, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 3)  # and no more after
        gcs.close()

        async def main() -> tuple[MavlinkLink, AutopilotState]:
            link = make_link(sitl.url(1), key=KEY)
            state = AutopilotState(link)
            commander = Commander(link, state, link.cfg)
            task = asyncio.ensure_future(link.run())
            try:
                while not link.connected:
                    await asyncio.sleep(0.05)
                await asyncio.wait_for(commander.request_autopilot_version(), 20)
            finally:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            return link, state

        link, state = asyncio.run(main())
        assert state.firmware is not None and state.firmware.label == "ArduPilot copter 4.0.5-rc"
        assert link.stats.bad_signatures == 0 and link.stats.parse_errors == 0
        # (unsigned_rejected: what ArduPilot sent before our first signed message reached it)
    finally:
        sitl.stop()
