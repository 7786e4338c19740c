"""Commands addressed to the companion itself (companion/mavlink/inbound.py) over real MAVLink 2 on
loopback UDP: a fake autopilot (tests/mavlink_peer.py) routes a ground station's COMMAND_LONG to
the link, as ArduPilot does, and carries the companion's COMMAND_ACK and STATUSTEXT back."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

from companion.daemon import Daemon
from companion.mavlink.inbound import InboundCommands
from companion.mavlink.link import MavlinkLink, mavlink
from tests.mavlink_peer import COMPANION_COMPID, FakeAutopilot
from tests.test_link_trust import run_with_fake

GCS = (255, 190)
RTL = mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH


def routed(fake: FakeAutopilot, sender: tuple[int, int], command: int, target_component: int = COMPANION_COMPID) -> None:
    """A COMMAND_LONG from ``sender`` (sysid, compid) to system 1 ``target_component``, as the
    autopilot forwards it (the sender's own ids on the frame)."""
    mav = fake.conn.mav
    mav.srcSystem, mav.srcComponent = sender
    try:
        mav.send(mavlink.MAVLink_command_long_message(1, target_component, command, 0, 0, 0, 0, 0, 0, 0, 0))
    finally:
        mav.srcSystem, mav.srcComponent = 1, 1


def acks(fake: FakeAutopilot) -> list[Any]:
    return [m for m in fake.received if m.get_type() == "COMMAND_ACK" and m.get_srcComponent() == COMPANION_COMPID]


def exchange(command: int, sender: tuple[int, int] = GCS, refuse: str | None = None,
             target_component: int = COMPANION_COMPID,
             fail: bool = False) -> tuple[list[Any], list[str], list[str], InboundCommands]:
    """Send one routed command to a companion that obeys RTL with a handler answering ``refuse``
    (or raising, with ``fail``); (its COMMAND_ACKs, its STATUSTEXTs, what the handler saw, the server)."""
    seen: list[str] = []
    texts: list[str] = []
    box: dict[str, Any] = {}

    async def body(link: MavlinkLink, fake: FakeAutopilot) -> None:
        server = box["server"] = InboundCommands(link, (255,), texts.append)
        box["fake"] = fake
        def handler(msg: Any) -> str | None:
            seen.append(f"{msg.get_srcSystem()}/{msg.get_srcComponent()}")
            if fail:
                raise RuntimeError("planner broke")
            return refuse

        server.register(RTL, handler)
        routed(fake, sender, command, target_component)
        if target_component == COMPANION_COMPID:
            await fake.until(lambda: acks(fake), "the companion's COMMAND_ACK")
        else:
            await asyncio.sleep(0.3)
            fake.pump()

    run_with_fake(body)
    return acks(box["fake"]), texts, seen, box["server"]


def test_a_ground_stations_command_to_the_companion_is_obeyed_and_acknowledged_to_it() -> None:
    answers, texts, seen, server = exchange(RTL)
    assert seen == ["255/190"]
    assert [(a.command, a.result, a.target_system, a.target_component) for a in answers] == [
        (RTL, mavlink.MAV_RESULT_ACCEPTED, *GCS)]
    assert texts == [] and server.stats.accepted == 1


def test_a_refused_command_is_denied_and_the_reason_told_as_statustext() -> None:
    answers, texts, _, server = exchange(RTL, refuse="not at the held altitude")
    assert [a.result for a in answers] == [mavlink.MAV_RESULT_DENIED]
    assert texts == ["companion: not at the held altitude"] and server.stats.denied == 1


def test_a_handler_that_raises_answers_failed_and_says_why() -> None:
    answers, texts, seen, server = exchange(RTL, fail=True)
    assert [a.result for a in answers] == [mavlink.MAV_RESULT_FAILED] and seen == ["255/190"]
    assert texts == ["companion: MAV_CMD_NAV_RETURN_TO_LAUNCH failed: RuntimeError: planner broke"]
    assert server.stats.failed == 1 and server.stats.accepted == 0


def test_a_command_without_a_handler_is_unsupported() -> None:
    answers, _, seen, server = exchange(mavlink.MAV_CMD_DO_SET_MODE)
    assert [a.result for a in answers] == [mavlink.MAV_RESULT_UNSUPPORTED] and seen == []
    assert server.stats.unsupported == 1


def test_a_system_not_in_command_sysids_is_denied_and_never_reaches_the_handler() -> None:
    answers, _, seen, server = exchange(RTL, sender=(42, 190))
    assert [a.result for a in answers] == [mavlink.MAV_RESULT_DENIED] and seen == []
    assert server.stats.refused_senders == 1


def test_a_command_addressed_to_another_component_is_not_the_companions() -> None:
    answers, _, seen, _ = exchange(RTL, target_component=1)
    assert answers == [] and seen == []


def test_a_return_commanded_when_no_mission_step_runs_is_denied_before_asking_the_pipeline() -> None:
    """The runner flies a takeover only inside its steps: after the mission ended (even airborne)
    an accepted return would have no one to fly it."""
    asked: list[str] = []
    ctx = SimpleNamespace(request_guidance=lambda reason: asked.append(reason))
    ended = SimpleNamespace(mission=SimpleNamespace(status="completed", ctx=ctx))
    running = SimpleNamespace(mission=SimpleNamespace(status="running", ctx=ctx))
    assert Daemon._commanded_return(ended, None) == "the mission is completed: nobody to fly the return"
    assert asked == []
    assert Daemon._commanded_return(running, None) is None and asked == ["MAVLink command"]
