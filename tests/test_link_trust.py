"""The companion trusts only its autopilot (companion/mavlink/trust.py, link.py, commands.py), over
real MAVLink 2 on loopback UDP: a fake autopilot (tests/mavlink_peer.py) or the built-in vehicle.

- the identity (ids, autopilot family, MAV_TYPE) is locked by the first HEARTBEAT; heartbeats
  claiming another are counted, reported and not obeyed, other components' are no conflict;
- one odd boot time is dropped and counted, not a reboot; a new, earlier clock confirmed by
  several stamps is; a real restart of the vehicle process (or of ArduPilot SITL) is one reboot;
- a COMMAND_ACK completes a command only from the autopilot, for a pending command, addressed to us.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from companion.health import State
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import Commander
from companion.mavlink.link import ALERT_HOLD_S, MavlinkLink, mavlink
from companion.mavlink.streams import StreamNegotiator
from companion.mavlink.trust import OLD_CLOCK_SILENT_S
from sitl.ardupilot import ArduPilotSitl, SitlOptions, default_defaults
from tests.ardupilot_helpers import ARDUCOPTER, requires_ardupilot
from tests.mavlink_peer import FakeAutopilot, make_link
from tests.sitl_helpers import Processes, vehicle_args
from tests.conftest import free_port

GUIDED = 4  # ArduCopter custom_mode
PX4_OFFBOARD = (6 << 16)  # PX4 main mode OFFBOARD in custom_mode
GIMBAL_COMPID = mavlink.MAV_COMP_ID_GIMBAL  # 154
REQUEST_MESSAGE = mavlink.MAV_CMD_REQUEST_MESSAGE


def run_with_fake(body: Callable[[MavlinkLink, FakeAutopilot], Awaitable[None]], **mavlink_cfg: float) -> MavlinkLink:
    """Run the link against a fake autopilot, connect them, then ``body(link, fake)``; the link afterwards."""
    fake = FakeAutopilot()

    async def main() -> MavlinkLink:
        link = make_link(fake.url, **mavlink_cfg)
        task = asyncio.ensure_future(link.run())
        try:
            await fake.connect(link)
            await body(link, fake)
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        return link

    try:
        return asyncio.run(main())
    finally:
        fake.close()


async def stream_attitude(link: MavlinkLink, fake: FakeAutopilot, count: int, offset_ms: int,
                          odd: dict[int, int] | None = None) -> None:
    """``count`` ATTITUDE at 50 Hz on the fake's clock started ``offset_ms`` earlier, and a HEARTBEAT
    every tenth; message i carries boot time ``odd[i]`` instead where given (with roll 1 as a marker)."""
    for i in range(count):
        if i % 10 == 0:
            fake.heartbeat()
        if odd and i in odd:
            fake.attitude(odd[i], roll=1.0)
        else:
            fake.attitude(fake.boot_ms(offset_ms))
        await asyncio.sleep(0.02)
    fake.pump()
    await asyncio.sleep(0.05)  # what is in flight arrives


# -- identity --------------------------------------------------------------------------------


def test_a_spoofed_px4_heartbeat_from_the_autopilot_ids_is_counted_and_the_autopilot_stays_ardupilot() -> None:
    state: dict[str, AutopilotState] = {}
    health: dict[str, dict] = {}

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        state["autopilot"] = AutopilotState(link)
        fake.heartbeat(custom_mode=GUIDED)
        await fake.until(lambda: state["autopilot"].mode == "GUIDED", "the autopilot's mode")
        for _ in range(4):  # what the review saw: a PX4 claim every 0.5 s, here faster
            fake.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_PX4, custom_mode=PX4_OFFBOARD)
            await asyncio.sleep(0.05)
        fake.heartbeat(mav_type=mavlink.MAV_TYPE_FIXED_WING)  # the same family, another vehicle type
        await fake.until(lambda: link.stats.identity_changed == 5, "5 refused HEARTBEATs")
        assert link.connected
        health["during"] = link.health.snapshot()["components"]["autopilot_identity"]
        await asyncio.sleep(ALERT_HOLD_S)
        fake.heartbeat(custom_mode=GUIDED)  # the real autopilot, a second after the last conflict
        await fake.until(lambda: link.health.get("autopilot_identity").state == State.OK, "identity ok again")

    link = run_with_fake(body)
    autopilot = state["autopilot"]
    assert link.autopilot == "ArduPilot"
    assert autopilot.firmware is not None and autopilot.firmware.label == "ArduPilot copter"
    assert autopilot.mode == "GUIDED"  # the spoofed modes were not taken either
    assert link.stats.identity_changed == 5 and link.stats.identity_impostors == 0
    identity = health["during"]
    assert identity["state"] == "degraded"
    assert "5 HEARTBEATs refused" in identity["reason"]
    assert "ArduPilot fixed_wing (sysid 1 compid 1)" in identity["reason"]
    after = link.health.snapshot()["components"]["autopilot_identity"]["reason"]
    assert after == "locked: ArduPilot quadrotor (sysid 1 compid 1); 5 conflicting HEARTBEATs refused before"


def test_an_autopilot_heartbeat_from_another_compid_is_an_impostor_a_gimbal_or_companion_is_not() -> None:
    health: dict[str, dict] = {}

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        fake.heartbeat(autopilot=mavlink.MAV_AUTOPILOT_INVALID, mav_type=mavlink.MAV_TYPE_GIMBAL, compid=GIMBAL_COMPID)
        fake.heartbeat(mav_type=mavlink.MAV_TYPE_ONBOARD_CONTROLLER, compid=191)  # another companion computer
        fake.heartbeat(mav_type=mavlink.MAV_TYPE_GPS, compid=125)  # an AP_Periph node: ArduPilot, but no vehicle
        await fake.until(lambda: link.stats.other_components_rx == 3, "the gimbal's, companion's and GPS's HEARTBEATs")
        health["before"] = link.health.snapshot()["components"]["autopilot_identity"]
        fake.heartbeat(compid=2)  # an autopilot at another component id of system 1
        await fake.until(lambda: link.stats.identity_impostors == 1, "the impostor")
        assert link.connected

    link = run_with_fake(body)
    assert health["before"] == {**health["before"], "state": "ok",
                                "reason": "locked: ArduPilot quadrotor (sysid 1 compid 1)"}
    assert link.stats.identity_changed == 0
    after = link.health.snapshot()["components"]["autopilot_identity"]
    assert after["state"] == "degraded"
    assert "ArduPilot quadrotor (sysid 1 compid 2): an autopilot at another component id" in after["reason"]
    assert link.autopilot == "ArduPilot"


# -- boot clock ------------------------------------------------------------------------------


def test_one_backwards_or_far_ahead_boot_time_is_dropped_and_counted_not_a_reboot() -> None:
    seen: list[int] = []
    connections: list[float] = []

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        link.subscribe("ATTITUDE", lambda msg: seen.append(msg.time_boot_ms))
        link.on_connect(lambda: connections.append(1.0))
        await stream_attitude(link, fake, 60, offset_ms=100_000, odd={20: 500, 40: 3_600_000_000})

    link = run_with_fake(body)
    assert link.stats.autopilot_reboots == 0
    assert link.stats.time_anomalies == 2
    assert 500 not in seen and 3_600_000_000 not in seen and len(seen) == 58
    assert seen == sorted(seen)
    assert connections == []  # nothing restarted: no origin re-sent, no streams re-requested, no state reset


def test_a_forger_interleaving_its_own_earlier_clock_with_the_real_one_makes_no_reboot() -> None:
    connections: list[float] = []

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        link.on_connect(lambda: connections.append(1.0))
        for i in range(100):  # 2 s: four forged stamps on a clock at 5 s for every real one at 100 s
            if i % 10 == 0:
                fake.heartbeat()
            fake.attitude(fake.boot_ms(100_000))
            for k in range(4):
                fake.attitude(5_000 + 20 * (4 * i + k), roll=1.0)
            await asyncio.sleep(0.02)
        fake.pump()
        await asyncio.sleep(0.05)

    link = run_with_fake(body)
    assert link.stats.autopilot_reboots == 0 and connections == []
    assert link.stats.time_anomalies == 400


def test_a_reboot_during_the_connection_is_confirmed_by_the_new_clock_and_starts_a_new_connection() -> None:
    seen: list[int] = []
    connections: list[float] = []

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        link.subscribe("ATTITUDE", lambda msg: seen.append(msg.time_boot_ms))
        link.on_connect(lambda: connections.append(1.0))
        await stream_attitude(link, fake, 20, offset_ms=100_000)
        await asyncio.sleep(OLD_CLOCK_SILENT_S)  # booting: silent
        await stream_attitude(link, fake, 20, offset_ms=-fake.boot_ms() + 300)  # rebooted: its clock at 300 ms

    link = run_with_fake(body)
    assert link.stats.autopilot_reboots == 1
    assert link.stats.time_anomalies == 2  # the new clock's first two stamps, before it was confirmed
    assert len(connections) == 1  # one new connection for the on_connect callbacks
    assert len(seen) == 38 and seen[20] < 1000 and seen[20:] == sorted(seen[20:])


@pytest.mark.parametrize("link_timeout_s", [0.5, 10.0], ids=["after-link-loss", "within-link-timeout"])
def test_the_built_in_vehicle_restarted_is_one_reboot(tmp_path: Path, procs: Processes, link_timeout_s: float) -> None:
    """The vehicle process killed (a power cut) and started again on the same port, with the same
    identity: its earlier boot clock counts as one reboot. After a link loss, or back before the
    link timed out: then it streams nothing until asked, and the stream watch asks again."""
    port = free_port()
    args = vehicle_args(port, log=None, position_source="extnav", gps=False)
    vehicle = procs.start("vehicle", args)
    clock_before: dict[str, int] = {}

    async def main() -> MavlinkLink:
        link = make_link(f"udpout:127.0.0.1:{port}", link_timeout_s=link_timeout_s)
        state = AutopilotState(link)
        streams = StreamNegotiator(link, state, Commander(link, state, link.cfg), link.cfg.streams, link.health)

        async def attitude_after(t: float) -> None:
            while state.attitude_time is None or state.attitude_time <= t:
                await asyncio.sleep(0.05)

        tasks = [asyncio.ensure_future(link.run()), asyncio.ensure_future(streams.run())]
        try:
            await asyncio.wait_for(attitude_after(0.0), 20)
            await asyncio.sleep(8.0)  # the vehicle's clock runs well past where the next one's will be
            clock_before["ms"] = link._boot_clock.ms or 0
            vehicle.kill()
            while link.connected and link_timeout_s < 1.0:
                await asyncio.sleep(0.05)
            assert link.connected == (link_timeout_s > 1.0)
            lost_at = asyncio.get_running_loop().time()
            procs.start("vehicle-again", args)
            await asyncio.wait_for(attitude_after(lost_at), 20)
            while link.stats.autopilot_reboots == 0 and asyncio.get_running_loop().time() < lost_at + 20:
                await asyncio.sleep(0.05)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        return link

    link = asyncio.run(main())
    assert clock_before["ms"] > 8000
    assert link.stats.autopilot_reboots == 1
    assert link.autopilot == "ArduPilot" and link.stats.identity_changed == 0
    assert link._boot_clock.ms is not None and link._boot_clock.ms < clock_before["ms"]


@requires_ardupilot
def test_ardupilot_sitl_killed_and_started_again_is_one_reboot(tmp_path: Path) -> None:
    """ArduCopter 4.0.5 SITL killed (SIGKILL) and started again without wiping: the TCP port ends, the
    link reopens it, the streams are asked for again and the earlier boot clock counts as one reboot."""
    sitl = ArduPilotSitl(SitlOptions(ARDUCOPTER, defaults=default_defaults(ARDUCOPTER),
                                     home=(1.2966, 103.7764, 10.0, 0.0)), tmp_path / "sitl")
    sitl.start(wipe=True)
    clock_before: dict[str, int] = {}

    async def main() -> MavlinkLink:
        assert sitl.wait_listening(30)
        link = make_link(sitl.url(0))
        state = AutopilotState(link)
        streams = StreamNegotiator(link, state, Commander(link, state, link.cfg), link.cfg.streams, link.health)
        tasks = [asyncio.ensure_future(link.run()), asyncio.ensure_future(streams.run())]
        loop = asyncio.get_running_loop()
        try:
            while (link._boot_clock.ms or 0) < 15_000:  # well past where the next boot will be when it streams
                await asyncio.sleep(0.1)
            clock_before["ms"] = link._boot_clock.ms or 0
            sitl.kill()
            sitl.start()
            assert await loop.run_in_executor(None, sitl.wait_listening, 30.0)
            deadline = loop.time() + 40
            while link.stats.autopilot_reboots == 0 and loop.time() < deadline:
                await asyncio.sleep(0.1)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        return link

    try:
        link = asyncio.run(main())
    finally:
        sitl.stop()
    assert link.stats.autopilot_reboots == 1 and link.stats.reconnects >= 1
    assert link._boot_clock.ms is not None and link._boot_clock.ms < clock_before["ms"]
    assert link.autopilot == "ArduPilot" and link.stats.identity_changed == link.stats.identity_impostors == 0


# -- COMMAND_ACK -----------------------------------------------------------------------------


def ack(command: int, result: int, target: tuple[int, int] = (0, 0)) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_command_ack_message(command, result, 0, 0, *target)


def test_forged_acks_do_not_complete_a_command_and_the_autopilot_s_own_does() -> None:
    outcome: dict[str, object] = {}

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        commander = Commander(link, AutopilotState(link), link.cfg)
        fake.send(ack(REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED, (1, 197)))  # nothing pending yet
        await fake.until(lambda: link.stats.acks_ignored == 1, "the ACK of no command")
        task = asyncio.ensure_future(commander.command_result(REQUEST_MESSAGE, 148))
        await fake.until(lambda: any(m.get_type() == "COMMAND_LONG" for m in fake.received), "the command")
        fake.send(ack(REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED, (1, 197)), compid=2)  # another component
        fake.send(ack(REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED, (7, 197)))  # for another system
        fake.send(ack(REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED, (1, 5)))  # for another component
        fake.send(ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_RESULT_ACCEPTED, (1, 197)))  # not pending
        await asyncio.sleep(0.3)
        outcome["done_by_forged"] = task.done()
        fake.send(ack(REQUEST_MESSAGE, mavlink.MAV_RESULT_DENIED, (1, 197)))
        outcome["result"] = await asyncio.wait_for(task, 2.0)
        fake.send(ack(REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED, (1, 197)))  # a repeat, after the answer
        await fake.until(lambda: link.stats.acks_ignored == 5, "the repeated ACK")

    link = run_with_fake(body, command_timeout_s=2.0, command_retries=1)
    assert outcome == {"done_by_forged": False, "result": mavlink.MAV_RESULT_DENIED}
    assert link.stats.acks_ignored == 5  # before any command, two misaddressed, not pending, the repeat
    assert link.stats.other_components_rx == 1  # the one from component 2 never reached the commander


def test_an_ack_with_no_targets_as_ardupilot_4_0_sends_completes_the_command() -> None:
    outcome: dict[str, object] = {}

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        commander = Commander(link, AutopilotState(link), link.cfg)
        task = asyncio.ensure_future(commander.command_result(REQUEST_MESSAGE, 148))
        await fake.until(lambda: any(m.get_type() == "COMMAND_LONG" for m in fake.received), "the command")
        fake.send(ack(REQUEST_MESSAGE, mavlink.MAV_RESULT_ACCEPTED))
        outcome["result"] = await asyncio.wait_for(task, 2.0)

    link = run_with_fake(body, command_timeout_s=2.0, command_retries=1)
    assert outcome["result"] == mavlink.MAV_RESULT_ACCEPTED and link.stats.acks_ignored == 0


# -- values ----------------------------------------------------------------------------------


def test_nonfinite_or_absurd_values_are_dropped_before_the_boot_clock_and_counted_per_type() -> None:
    """A NaN ATTITUDE stamped ahead of the real clock would, if its stamp were taken, hide the real
    ATTITUDEs stamped before it; it is dropped first. An IMU reading of 1e9 m/s^2 is dropped too."""
    seen: list[float] = []
    health: dict[str, dict] = {}

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        link.subscribe("ATTITUDE", lambda msg: seen.append(msg.roll))
        link.subscribe("HIGHRES_IMU", lambda msg: seen.append(msg.xacc))
        fake.heartbeat()
        for i in range(30):
            fake.attitude(fake.boot_ms(100_000), roll=0.1)
            if i % 3 == 0:
                fake.attitude(fake.boot_ms(100_800), roll=math.nan)
                fake.send(mavlink.MAVLink_highres_imu_message(fake.boot_ms(100_000) * 1000, 1e9, 0, -9.8, 0, 0, 0,
                                                              0, 0, 0, 1013.0, 0, 0, 20.0, 0xFFFF))
            await asyncio.sleep(0.02)
        await fake.until(lambda: sum(link.stats.values_rejected.values()) == 20, "20 refused messages")
        health["during"] = link.health.snapshot()["components"]["autopilot_values"]
        await asyncio.sleep(ALERT_HOLD_S)
        fake.attitude(fake.boot_ms(100_000), roll=0.1)
        await fake.until(lambda: link.health.get("autopilot_values").state == State.OK, "values ok again")

    link = run_with_fake(body)
    assert seen == pytest.approx([0.1] * 31)  # every real ATTITUDE, nothing else
    assert link.stats.values_rejected == {"ATTITUDE": 10, "HIGHRES_IMU": 10}
    assert link.stats.time_anomalies == 0
    assert health["during"]["state"] == "degraded" and "20 messages dropped" in health["during"]["reason"]
