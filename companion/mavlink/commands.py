"""Commands to the autopilot with COMMAND_ACK handling: modes, arming, takeoff, landing, messages.

Every command is COMMAND_LONG, retried ``command_retries`` times (with the confirmation field
counting retries) and waited for ``command_timeout_s`` each time. A command that is refused
or never acknowledged raises :class:`CommandFailed` naming the command and the result
(:meth:`Commander.command_result` returns the result instead, for callers that try
alternatives, e.g. the stream negotiation).

A COMMAND_ACK completes a command only if it comes from the autopilot (the link passes on
nothing else), names a command of ours that is waiting for its ACK, and, where its MAVLink 2
``target_system`` / ``target_component`` are filled in (non-zero), names us. Any other is ignored
and counted (``link.stats.acks_ignored``): a late or repeated ACK, one meant for a ground station,
or a forged one. ArduPilot 4.0 leaves both targets 0 (checked against ArduCopter 4.0.5 SITL).
"""

from __future__ import annotations

import asyncio
import logging
from collections import defaultdict

from companion.config import MavlinkConfig, PayloadConfig
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.link import MavlinkLink, mavlink, run_per_connection

log = logging.getLogger("companion.commands")

VERSION_WAIT_S = 0.5  # AUTOPILOT_VERSION expected this long after a request
VERSION_ATTEMPTS = 3
RESULT_NAMES = {v: k for k, v in vars(mavlink).items() if k.startswith("MAV_RESULT_") and isinstance(v, int)}
COMMAND_NAMES = {v: k for k, v in vars(mavlink).items() if k.startswith("MAV_CMD_") and isinstance(v, int)}


class CommandFailed(Exception):
    """The autopilot refused a command or never acknowledged it."""


class Commander:
    """Sends commands and waits for their COMMAND_ACK."""

    def __init__(self, link: MavlinkLink, state: AutopilotState, cfg: MavlinkConfig) -> None:
        self.link = link
        self.state = state
        self.cfg = cfg
        self._waiting: dict[int, asyncio.Future[int]] = {}
        # COMMAND_ACK names only the command: two of the same at once could not be told apart.
        self._locks: dict[int, asyncio.Lock] = defaultdict(asyncio.Lock)
        self._connected = asyncio.Event()  # set on every (re)connection: identify the firmware again
        link.subscribe("COMMAND_ACK", self._on_ack)
        link.on_connect(self._connected.set)

    async def command_result(self, command: int, *params: float) -> int | None:
        """Send COMMAND_LONG ``command`` with up to 7 params; its final MAV_RESULT, or None if never acknowledged."""
        async with self._locks[command]:
            return await self._command_result(command, [float(p) for p in params] + [0.0] * (7 - len(params)))

    async def _command_result(self, command: int, padded: list[float]) -> int | None:
        loop = asyncio.get_running_loop()
        for attempt in range(self.cfg.command_retries):
            future: asyncio.Future[int] = loop.create_future()
            self._waiting[command] = future
            self.link.send(mavlink.MAVLink_command_long_message(*self.link.target(), command, attempt, *padded))
            try:
                result = await asyncio.wait_for(future, self.cfg.command_timeout_s)
            except TimeoutError:
                log.debug("%s: no COMMAND_ACK (attempt %d)", COMMAND_NAMES.get(command, command), attempt + 1)
                continue
            finally:
                self._waiting.pop(command, None)
            if result == mavlink.MAV_RESULT_IN_PROGRESS:
                continue
            return result
        return None

    async def command(self, command: int, *params: float) -> None:
        """Send COMMAND_LONG ``command`` with up to 7 params; raise CommandFailed unless ACCEPTED."""
        name = COMMAND_NAMES.get(command, str(command))
        result = await self.command_result(command, *params)
        if result is None:
            raise CommandFailed(f"{name}: no COMMAND_ACK after {self.cfg.command_retries} attempts")
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise CommandFailed(f"{name} refused: {RESULT_NAMES.get(result, result)}")

    async def identify_every_connection(self) -> None:
        """Supervised task body: :meth:`request_autopilot_version` after every (re)connection (the
        firmware decides frames and setpoints; a reboot may have brought another version)."""
        await run_per_connection(self._connected, self.request_autopilot_version)

    async def request_autopilot_version(self) -> None:
        """Ask for AUTOPILOT_VERSION until it arrives or ``VERSION_ATTEMPTS`` rounds passed:
        REQUEST_MESSAGE, then the older REQUEST_AUTOPILOT_CAPABILITIES (ArduPilot 4.0 accepts
        REQUEST_MESSAGE for it without sending it, and answers the older command only from the
        second time on)."""
        for _ in range(VERSION_ATTEMPTS):
            for command, params in ((mavlink.MAV_CMD_REQUEST_MESSAGE, (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION,)),
                                    (mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, (1,))):
                await self.command_result(command, *params)
                await asyncio.sleep(VERSION_WAIT_S)
                if self.state.firmware is not None and self.state.firmware.version is not None:
                    return
        log.warning("no AUTOPILOT_VERSION: the firmware version is unknown (setpoints without acceleration)")

    async def request_message(self, msg_id: int) -> None:
        """Ask the autopilot to send message ``msg_id`` once (MAV_CMD_REQUEST_MESSAGE)."""
        await self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, msg_id)

    async def set_mode(self, name: str) -> None:
        """Switch to flight mode ``name`` (e.g. GUIDED, LAND; PX4: OFFBOARD, LAND)."""
        base, custom = self.state.custom_mode_for(name)
        if self.link.autopilot == "PX4":
            await self.command(mavlink.MAV_CMD_DO_SET_MODE, base, (custom >> 16) & 0xFF, (custom >> 24) & 0xFF)
        else:
            await self.command(mavlink.MAV_CMD_DO_SET_MODE, base, custom)

    async def arm(self) -> None:
        await self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)

    async def disarm(self) -> None:
        await self.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0)

    async def takeoff(self, altitude_m: float) -> None:
        """Take off to ``altitude_m`` above home (ArduPilot GUIDED: param7 is relative)."""
        await self.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, altitude_m)

    async def release_payload(self, payload: PayloadConfig) -> None:
        """Release the payload: DO_SET_SERVO to the release PWM, or DO_GRIPPER release."""
        if payload.command == "gripper":
            await self.command(mavlink.MAV_CMD_DO_GRIPPER, payload.gripper, mavlink.GRIPPER_ACTION_RELEASE)
        else:
            await self.command(mavlink.MAV_CMD_DO_SET_SERVO, payload.servo, payload.release_pwm)

    @property
    def landing_mode(self) -> str:
        """The mode :meth:`land` switches to: LAND; RTL for a fixed wing, which has no LAND mode
        (ArduPlane lands in AUTO from a mission's landing sequence, or by its pilot): it flies home
        and circles there at its RTL altitude."""
        firmware = self.state.firmware
        return "RTL" if firmware is not None and firmware.vehicle == "plane" else "LAND"

    async def land(self) -> None:
        """Switch the autopilot to :attr:`landing_mode`."""
        await self.set_mode(self.landing_mode)

    def _on_ack(self, msg: mavlink.MAVLink_message) -> None:
        future = self._waiting.get(msg.command)
        refusal = self._ack_refusal(msg, future)
        if refusal is not None:
            self.link.stats.acks_ignored += 1
            log.debug("ignored a COMMAND_ACK of %s: %s", COMMAND_NAMES.get(msg.command, msg.command), refusal)
            return
        assert future is not None
        future.set_result(msg.result)

    def _ack_refusal(self, msg: mavlink.MAVLink_message, future: asyncio.Future[int] | None) -> str | None:
        """Why COMMAND_ACK ``msg`` does not complete ``future`` (the command's, if it is waiting); None if it does."""
        if future is None or future.done():
            return "no such command of ours is waiting for its ACK"
        ids = self.link.ids
        for field, ours in (("target_system", ids.sysid), ("target_component", ids.compid)):
            named = getattr(msg, field, 0)
            if named not in (0, ours):
                return f"addressed to {field} {named}, not {ours}"
        return None
