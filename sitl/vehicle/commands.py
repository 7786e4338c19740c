"""Commands to the simulated vehicle: COMMAND_LONG / COMMAND_INT, their handlers and the COMMAND_ACK."""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mav

from sitl.vehicle.link import HEARTBEAT_INTERVAL_US, Link
from sitl.vehicle.receiving import finite

DEFAULT_STREAM_INTERVAL_US = 250_000  # SET_MESSAGE_INTERVAL with interval 0: "default rate", 4 Hz
FORCE_MAGIC = 21196  # COMPONENT_ARM_DISARM param2 that skips checks
# COMMAND_INT commands whose x/y are latitude/longitude in degE7 (params 5/6 in degrees).
LATLON_COMMANDS = frozenset({mav.MAV_CMD_DO_SET_HOME, mav.MAV_CMD_NAV_TAKEOFF, mav.MAV_CMD_NAV_LAND})
AMSL_FRAMES = frozenset({mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_INT})
RELATIVE_FRAMES = frozenset({mav.MAV_FRAME_GLOBAL_RELATIVE_ALT, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT})


class CommandsMixin:
    """Part of :class:`sitl.vehicle.core.Vehicle` (which sets the attributes): commands and their ACKs."""

    def _on_command_long(self, link: Link, msg: mav.MAVLink_message) -> None:
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._run_command(link, msg, msg.command, params, None)

    def _on_command_int(self, link: Link, msg: mav.MAVLink_message) -> None:
        """COMMAND_INT: x/y are degE7 for positional commands, plain integers otherwise."""
        scale = 1e-7 if msg.command in LATLON_COMMANDS else 1.0
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.x * scale, msg.y * scale, msg.z)
        self._run_command(link, msg, msg.command, params, msg.frame)

    def _run_command(self, link: Link, msg: mav.MAVLink_message, command: int,
                     params: tuple[float, ...], frame: int | None) -> None:
        """Handle a command, ACK it, then send what it asked for (ArduPilot's order)."""
        self._replies = []
        handler = self._commands.get(command)
        try:
            result = handler(link, params, frame) if handler else mav.MAV_RESULT_UNSUPPORTED
        except (ValueError, OverflowError):  # int() of a NaN or infinite parameter
            self._nonfinite += 1
            result = mav.MAV_RESULT_DENIED
        self._ack(link, msg, command, result)
        for reply in self._replies:
            link.send(reply)

    def _ack(self, link: Link, msg: mav.MAVLink_message, command: int, result: int) -> None:
        """COMMAND_ACK to the sender (progress and result_param2 0, as ArduPilot) and log it."""
        link.send(mav.MAVLink_command_ack_message(
            command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        self.log.add_command(self._now(), command, result)

    def _cmd_set_message_interval(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 message id, param2 interval us (0 default rate, -1 off)."""
        if self.cfg.legacy_streams:
            return mav.MAV_RESULT_UNSUPPORTED
        msgid = int(p[0])
        refused = msgid in self.cfg.refuse_intervals  # answered as ArduPilot 4.0 does (FAILED)
        if refused or msgid not in self._builders:
            self._texts.append((mav.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msgid})"))
            return mav.MAV_RESULT_FAILED if refused else mav.MAV_RESULT_DENIED
        if p[1] < 0:
            interval: int | None = None
        elif p[1] == 0:
            interval = HEARTBEAT_INTERVAL_US if msgid == mav.MAVLINK_MSG_ID_HEARTBEAT else DEFAULT_STREAM_INTERVAL_US
        else:
            interval = int(round(p[1]))
        link.set_interval(msgid, interval, self.t_us)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_get_message_interval(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        msgid = int(p[0])
        if msgid not in self._builders:
            return mav.MAV_RESULT_DENIED
        self._replies.append(mav.MAVLink_message_interval_message(msgid, link.intervals_us.get(msgid, -1)))
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_request_message(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 message id: sent once now if there is something to send."""
        builder = self._requestable.get(int(p[0]))
        if builder is None:
            return mav.MAV_RESULT_FAILED
        msg = builder()
        if msg is not None:
            self._replies.append(msg)
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_request_capabilities(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        self._replies.append(self._autopilot_version())
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_do_set_mode(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 base mode (CUSTOM_MODE_ENABLED), param2 custom (copter) mode."""
        return self._set_mode(int(p[0]), int(p[1]))

    def _set_mode(self, base_mode: int, custom_mode: int) -> int:
        if not base_mode & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return mav.MAV_RESULT_UNSUPPORTED
        ok, reason = self.copter.set_mode(custom_mode)
        if ok:
            return mav.MAV_RESULT_ACCEPTED
        text = reason if reason.startswith("Mode change") else f"Mode change failed: {reason}"
        self._texts.append((mav.MAV_SEVERITY_WARNING, text))
        return mav.MAV_RESULT_FAILED

    def _cmd_arm_disarm(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 1 arm / 0 disarm, param2 21196 forces."""
        force = p[1] == FORCE_MAGIC
        if p[0] == 1:
            ok, _ = self.copter.arm(force=force)
        elif p[0] == 0:
            ok, _ = self.copter.disarm(force=force)
        else:
            return mav.MAV_RESULT_UNSUPPORTED
        return mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED

    def _cmd_takeoff(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param7 altitude above home (m)."""
        ok, _ = self.copter.takeoff(p[6])
        return mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED

    def _cmd_land(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        ok, _ = self.copter.land()
        return mav.MAV_RESULT_ACCEPTED if ok else mav.MAV_RESULT_FAILED

    def _cmd_set_servo(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 output number (1..32), param2 PWM (us); the flight log's commands record it."""
        if not (1 <= int(p[0]) <= 32 and 500 <= int(p[1]) <= 2500):
            return mav.MAV_RESULT_DENIED
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_gripper(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 gripper instance (>= 1), param2 GRIPPER_ACTIONS (0 release, 1 grab)."""
        if int(p[0]) < 1 or int(p[1]) not in (mav.GRIPPER_ACTION_RELEASE, mav.GRIPPER_ACTION_GRAB):
            return mav.MAV_RESULT_DENIED
        if int(p[1]) == mav.GRIPPER_ACTION_RELEASE:
            self._texts.append((mav.MAV_SEVERITY_INFO, "Gripper load released"))
        return mav.MAV_RESULT_ACCEPTED

    def _cmd_set_home(self, link: Link, p: tuple[float, ...], frame: int | None) -> int:
        """param1 1: current position; else param5/6 lat/lon (deg), param7 alt (m AMSL, or per frame)."""
        if p[0] == 1:
            location = self._estimated_location()
            if location is None:
                return mav.MAV_RESULT_FAILED
            lat, lon, alt = location
        else:
            lat, lon, alt = p[4], p[5], p[6]
            if frame in RELATIVE_FRAMES and self.copter.home_position is not None:
                alt += self.copter.home_position[2]
            elif frame is not None and frame not in AMSL_FRAMES:
                return mav.MAV_RESULT_DENIED
            if not (finite((lat, lon, alt)) and abs(lat) <= 90 and abs(lon) <= 180):
                return mav.MAV_RESULT_FAILED
        self.copter.set_home(lat, lon, alt)
        self._last_home = None  # _observe announces it after the ACK
        return mav.MAV_RESULT_ACCEPTED
