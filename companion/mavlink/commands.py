"""Commands to the autopilot with COMMAND_ACK handling: streams, modes, arming, takeoff, landing.

Every command is COMMAND_LONG, retried ``command_retries`` times (with the confirmation field
counting retries) and waited for ``command_timeout_s`` each time. A command that is refused
or never acknowledged raises :class:`CommandFailed` naming the command and the result.
"""

from __future__ import annotations

import asyncio
import logging

from companion.config import MavlinkConfig, PayloadConfig, StreamRatesConfig
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.link import MavlinkLink, mavlink

log = logging.getLogger("companion.commands")

RESULT_NAMES = {v: k for k, v in vars(mavlink).items() if k.startswith("MAV_RESULT_") and isinstance(v, int)}
COMMAND_NAMES = {v: k for k, v in vars(mavlink).items() if k.startswith("MAV_CMD_") and isinstance(v, int)}


class CommandFailed(Exception):
    """The autopilot refused a command or never acknowledged it."""


def stream_requests(rates: StreamRatesConfig, autopilot: str | None) -> dict[int, float]:
    """{message id: rate Hz} to ask of the autopilot, for its flavour (0 Hz entries left out)."""
    estimator = mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS if autopilot == "PX4" else mavlink.MAVLINK_MSG_ID_EKF_STATUS_REPORT
    wanted = {
        mavlink.MAVLINK_MSG_ID_ATTITUDE: rates.attitude,
        mavlink.MAVLINK_MSG_ID_HIGHRES_IMU: rates.imu,
        mavlink.MAVLINK_MSG_ID_SCALED_IMU: rates.imu if autopilot != "PX4" else 0.0,
        mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: rates.local_position,
        mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: rates.gps_raw,
        mavlink.MAVLINK_MSG_ID_HOME_POSITION: rates.home_position,
        estimator: rates.estimator_status,
        mavlink.MAVLINK_MSG_ID_SIM_STATE: rates.sim_state,
    }
    return {msg_id: hz for msg_id, hz in wanted.items() if hz > 0}


class Commander:
    """Sends commands and waits for their COMMAND_ACK."""

    def __init__(self, link: MavlinkLink, state: AutopilotState, cfg: MavlinkConfig) -> None:
        self.link = link
        self.state = state
        self.cfg = cfg
        self._waiting: dict[int, asyncio.Future[int]] = {}
        link.subscribe("COMMAND_ACK", self._on_ack)

    async def command(self, command: int, *params: float) -> None:
        """Send COMMAND_LONG ``command`` with up to 7 params; raise CommandFailed unless ACCEPTED."""
        padded = [float(p) for p in params] + [0.0] * (7 - len(params))
        name = COMMAND_NAMES.get(command, str(command))
        loop = asyncio.get_running_loop()
        for attempt in range(self.cfg.command_retries):
            future: asyncio.Future[int] = loop.create_future()
            self._waiting[command] = future
            self.link.send(mavlink.MAVLink_command_long_message(*self.link.target(), command, attempt, *padded))
            try:
                result = await asyncio.wait_for(future, self.cfg.command_timeout_s)
            except TimeoutError:
                log.debug("%s: no COMMAND_ACK (attempt %d)", name, attempt + 1)
                continue
            finally:
                self._waiting.pop(command, None)
            if result == mavlink.MAV_RESULT_IN_PROGRESS:
                continue
            if result != mavlink.MAV_RESULT_ACCEPTED:
                raise CommandFailed(f"{name} refused: {RESULT_NAMES.get(result, result)}")
            return
        raise CommandFailed(f"{name}: no COMMAND_ACK after {self.cfg.command_retries} attempts")

    async def request_streams(self) -> None:
        """Ask for every configured stream with SET_MESSAGE_INTERVAL; log refusals, never raise."""
        for msg_id, hz in stream_requests(self.cfg.streams, self.link.autopilot).items():
            try:
                await self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
            except CommandFailed as exc:
                log.warning("stream %d at %g Hz: %s", msg_id, hz, exc)

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

    async def land(self) -> None:
        """Switch the autopilot to LAND."""
        await self.set_mode("LAND")

    def _on_ack(self, msg: mavlink.MAVLink_message) -> None:
        future = self._waiting.get(msg.command)
        if future is not None and not future.done():
            future.set_result(msg.result)
