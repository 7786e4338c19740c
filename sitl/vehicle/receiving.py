"""Receiving on the simulated vehicle: routing between links and the handlers of non-command messages."""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.frames import ned_from_geodetic
from companion.mavlink.setpoints import GUIDED_WAYPOINT_CURRENT, Setpoint
from sitl.vehicle.link import COMPID, Link

# Frames of a guided waypoint ArduPilot 4.0 takes (it answers the *_INT frames MAV_MISSION_UNSUPPORTED_FRAME)
WAYPOINT_FRAMES = frozenset({mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_GLOBAL_RELATIVE_ALT})

# ArduPilot's stream groups (REQUEST_DATA_STREAM), approximately.
STREAM_GROUPS: dict[int, tuple[int, ...]] = {
    mav.MAV_DATA_STREAM_RAW_SENSORS: (
        mav.MAVLINK_MSG_ID_RAW_IMU, mav.MAVLINK_MSG_ID_SCALED_IMU, mav.MAVLINK_MSG_ID_HIGHRES_IMU),
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: (
        mav.MAVLINK_MSG_ID_SYS_STATUS, mav.MAVLINK_MSG_ID_GPS_RAW_INT, mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE),
    mav.MAV_DATA_STREAM_POSITION: (
        mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED),
    mav.MAV_DATA_STREAM_EXTRA1: (mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_SIM_STATE),
    mav.MAV_DATA_STREAM_EXTRA2: (mav.MAVLINK_MSG_ID_VFR_HUD,),
    mav.MAV_DATA_STREAM_EXTRA3: (
        mav.MAVLINK_MSG_ID_SYSTEM_TIME, mav.MAVLINK_MSG_ID_BATTERY_STATUS, mav.MAVLINK_MSG_ID_EKF_STATUS_REPORT),
}


def finite(values: Sequence[float]) -> bool:
    """True if no value is NaN or infinite (received numbers are checked before use)."""
    return all(math.isfinite(v) for v in values)


def _covariance(msg: mav.MAVLink_message) -> list[float] | None:
    """A VISION_* covariance as sent, or None ("unknown") when any entry is non-finite."""
    return list(msg.covariance) if finite(msg.covariance) else None


class ReceivingMixin:
    """Part of :class:`sitl.vehicle.core.Vehicle` (which sets the attributes): incoming messages."""

    def _service_all(self) -> bool:
        """Handle every waiting message on every link; True if the awaited lockstep reply came."""
        replied = False
        for link in self.links:
            replied = self._service(link) or replied
        return replied

    def _service(self, link: Link) -> bool:
        """Handle a link's waiting messages in order; stops after the awaited lockstep reply."""
        while True:
            msg = link.recv()
            if msg is None:
                return False
            if self._dispatch(link, msg):
                return True

    def _dispatch(self, link: Link, msg: mav.MAVLink_message) -> bool:
        """Route and handle one message; True if it is the awaited lockstep reply."""
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return False
        if mtype == "TIMESYNC":
            return self._on_timesync(link, msg)
        target_system = getattr(msg, "target_system", 0)
        target_component = getattr(msg, "target_component", 0)
        for_me = target_system in (0, self.sysid) and target_component in (0, COMPID)
        if not (target_system == self.sysid and target_component in (0, COMPID)):
            for other in self.links:
                if other is not link:
                    other.forward(msg)
        handler = self._handlers.get(mtype)
        if for_me and handler is not None:
            handler(link, msg)
            self._observe()
        return False

    def _signature_refused(self, signed: bool) -> None:
        """Signing on: an unsigned (``signed`` False) or badly signed message on the companion link was dropped."""
        counts = self.log.signing
        if counts["unsigned_rejected"] + counts["bad_signatures"] == 0:
            print(f"sitl.vehicle: dropped {'a badly signed' if signed else 'an unsigned'} message on the companion "
                  "link (--signing-key): does the companion sign with the same key (mavlink.signing_key_file)?",
                  file=sys.stderr, flush=True)
        counts["bad_signatures" if signed else "unsigned_rejected"] += 1

    def _on_timesync(self, link: Link, msg: mav.MAVLink_message) -> bool:
        """Answer TIMESYNC requests; recognise the companion's reply to the lockstep tick."""
        if msg.tc1 == 0:
            now_ns = self.t_us * 1000 if self.cfg.lockstep else int(self._now() * 1e9)
            link.send(mav.MAVLink_timesync_message(max(1, now_ns), msg.ts1))
            return False
        return link is self.companion and self._awaited_ts1 is not None and msg.ts1 == self._awaited_ts1

    def _on_heartbeat(self, link: Link, msg: mav.MAVLink_message) -> None:
        if link is self.companion and msg.get_srcComponent() != COMPID:
            self._companion_heard = True

    def _on_set_mode(self, link: Link, msg: mav.MAVLink_message) -> None:
        result = self._set_mode(msg.base_mode, msg.custom_mode)
        self._ack(link, msg, mav.MAVLINK_MSG_ID_SET_MODE, result)

    def _on_request_data_stream(self, link: Link, msg: mav.MAVLink_message) -> None:
        """Legacy stream groups: rate Hz, or stop when start_stop is 0 or the rate is 0."""
        groups = STREAM_GROUPS.values() if msg.req_stream_id == mav.MAV_DATA_STREAM_ALL else (
            [STREAM_GROUPS[msg.req_stream_id]] if msg.req_stream_id in STREAM_GROUPS else [])
        on = msg.start_stop != 0 and msg.req_message_rate > 0
        interval = int(round(1e6 / msg.req_message_rate)) if on else None
        for group in groups:
            for msgid in group:
                link.set_interval(msgid, interval, self.t_us)

    def _on_set_gps_global_origin(self, link: Link, msg: mav.MAVLink_message) -> None:
        """Set the EKF origin (only if none yet) and confirm with GPS_GLOBAL_ORIGIN, like ArduPilot."""
        if self.copter.set_origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3):
            origin = self._gps_global_origin()
            if origin is not None:
                link.send(origin)

    def _on_set_home_position(self, link: Link, msg: mav.MAVLink_message) -> None:
        self.copter.set_home(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        self._last_home = None  # _observe announces it

    def _on_vision_position(self, link: Link, msg: mav.MAVLink_message) -> None:
        """VISION_POSITION_ESTIMATE: world-frame position (m) and ZYX Euler (rad) at ``usec``."""
        t_rx = self._now()
        pos = (msg.x, msg.y, msg.z)
        euler = (msg.roll, msg.pitch, msg.yaw)
        self.log.add_vision_position(t_rx, msg.usec, pos, euler, msg.reset_counter, msg.covariance)
        t_capture = self._vision_capture_time(link, msg.usec, t_rx, pos + euler)
        if t_capture is not None:
            self.copter.vision_position(t_capture, np.array(pos), np.array(euler), _covariance(msg), msg.reset_counter)

    def _on_vision_speed(self, link: Link, msg: mav.MAVLink_message) -> None:
        """VISION_SPEED_ESTIMATE: world-frame velocity (m/s) at ``usec``."""
        t_rx = self._now()
        vel = (msg.x, msg.y, msg.z)
        self.log.add_vision_speed(t_rx, msg.usec, vel)
        t_capture = self._vision_capture_time(link, msg.usec, t_rx, vel)
        if t_capture is not None:
            self.copter.vision_speed(t_capture, np.array(vel), _covariance(msg), msg.reset_counter)

    def _on_distance_sensor(self, link: Link, msg: mav.MAVLink_message) -> None:
        """DISTANCE_SENSOR (e.g. a pipeline's height above ground): logged for the report, not flown on."""
        self.log.add_distance_sensor(self._now(), msg.time_boot_ms, msg.id, msg.orientation, msg.current_distance,
                                     msg.min_distance, msg.max_distance)

    def _vision_capture_time(self, link: Link, usec: int, t_rx: float, values: tuple[float, ...]) -> float | None:
        """Sim time of a vision sample, or None (counted) if a value is non-finite or the stamp is dropped."""
        if not finite(values):
            self._nonfinite += 1
            return None
        return self._capture_time(link, usec, t_rx)

    def _capture_time(self, link: Link, usec: int, t_rx: float) -> float | None:
        """Sim time of a companion capture stamp (JitterCorrection); None (counted) if dropped."""
        t_capture = link.jitter.correct(usec * 1e-6, t_rx)
        if t_capture is None:
            self._stale_or_future += 1
        return t_capture

    def _on_set_position_target(self, link: Link, msg: mav.MAVLink_message) -> None:
        """SET_POSITION_TARGET_LOCAL_NED addressed to this system -> the copter's guided controller."""
        if msg.target_system != self.sysid:
            return
        pos, vel, acc = (msg.x, msg.y, msg.z), (msg.vx, msg.vy, msg.vz), (msg.afx, msg.afy, msg.afz)
        self.log.add_setpoint(self._now(), msg.coordinate_frame, msg.type_mask, pos, vel, acc)
        self.copter.set_position_target(
            msg.coordinate_frame, msg.type_mask, np.array(pos), np.array(vel), np.array(acc),
            msg.yaw, msg.yaw_rate)

    def _on_mission_item_int(self, link: Link, msg: mav.MAVLink_message) -> None:
        """MISSION_ITEM_INT with current 2: a guided waypoint (ArduPlane's "fly to here"), flown as a
        position target; answered by MISSION_ACK. Mission upload is not simulated (no other current)."""
        if msg.target_system != self.sysid or msg.current != GUIDED_WAYPOINT_CURRENT:
            return
        lat, lon, alt = msg.x * 1e-7, msg.y * 1e-7, float(msg.z)
        origin, home = self.copter.origin, self.copter.home_position
        result = mav.MAV_MISSION_UNSUPPORTED_FRAME
        if msg.frame in WAYPOINT_FRAMES and msg.command == mav.MAV_CMD_NAV_WAYPOINT and origin is not None:
            if msg.frame == mav.MAV_FRAME_GLOBAL_RELATIVE_ALT:
                alt += home[2] if home is not None else origin[2]
            pos = ned_from_geodetic(lat, lon, alt, tuple(origin))
            mask = Setpoint(position_ned=pos).type_mask  # position only, no yaw
            self.log.add_setpoint(self._now(), mav.MAV_FRAME_LOCAL_NED, mask, pos, (0, 0, 0), (0, 0, 0))
            taken = finite((lat, lon, alt)) and self.copter.set_position_target(
                mav.MAV_FRAME_LOCAL_NED, mask, pos, np.zeros(3), np.zeros(3), 0.0, 0.0)
            result = mav.MAV_MISSION_ACCEPTED if taken else mav.MAV_MISSION_ERROR
        link.send(mav.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), result,
                                                  mav.MAV_MISSION_TYPE_MISSION))
