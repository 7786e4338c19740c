"""State tracking of the simulated vehicle: what it announces and logs when the copter's state changes."""

from __future__ import annotations

from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.frames import geodetic_from_ned

STATUSTEXT_LEN = 50


class StateTrackingMixin:
    """Part of :class:`sitl.vehicle.core.Vehicle` (which sets the attributes): state changes, flight log."""

    def _observe(self) -> None:
        """After a step or a handled message: statustexts, mode, origin and home changes."""
        now = self._now()
        texts, self._texts = self._texts + self.copter.drain_statustext(), []
        for severity, text in texts:
            self._statustext(severity, text)
        self.log.add_mode(now, self.copter.mode_name, self.copter.armed)
        if self.copter.mode != self._announced_mode:
            # ArduPilot's set_mode() sends a HEARTBEAT on every link at once
            # (gcs().send_message(MSG_HEARTBEAT)): a companion learns of a pilot takeover
            # without waiting for the 1 Hz stream.
            self._announced_mode = self.copter.mode
            heartbeat = self._heartbeat()
            for link in self.links:
                link.send(heartbeat)
        origin = self.copter.origin
        if origin is not None:
            self.log.set_origin(now, *origin)
        home = self.copter.home_position
        if home is not None and tuple(home) != self._last_home:
            self._announce_home()

    def _announce_home(self) -> None:
        """HOME_POSITION and GPS_GLOBAL_ORIGIN to every link, as ArduPilot does on a new home."""
        home = self.copter.home_position
        self._last_home = None if home is None else tuple(home)
        for build in (self._home_position, self._gps_global_origin):
            msg = build()
            if msg is not None:
                for link in self.links:
                    link.send(msg)

    def _statustext(self, severity: int, text: str) -> None:
        """STATUSTEXT on every link (truncated to 50 characters, as ArduPilot) and in the log."""
        self.log.add_statustext(self._now(), severity, text)
        wire = text.encode("ascii", "replace")[:STATUSTEXT_LEN]
        msg = mav.MAVLink_statustext_message(severity, wire, 0, 0)
        for link in self.links:
            link.send(msg)

    def _record_sample(self) -> None:
        truth, est = self.copter.truth, self.copter.estimate
        self.log.sample(self.t, truth_pos=truth.pos_ned, truth_vel=truth.vel_ned, truth_euler=truth.euler,
                        est_valid=est.pos_valid, est_pos=est.pos_ned)

    def _write_log(self) -> None:
        if self.cfg.log is None:
            return
        self.log.rejected = {
            "nonfinite": self._nonfinite + int(self.copter.nonfinite_rejected),
            "stale_or_future": self._stale_or_future,
            "gated": int(self.copter.estimate.rejected_ext_nav),
        }
        self.log.write(self.cfg.log, self.t)

    def _estimated_location(self) -> tuple[float, float, float] | None:
        """(lat deg, lon deg, alt m AMSL) of the estimate, None without a valid position and origin."""
        origin = self.copter.origin
        if origin is None or not self.copter.estimate.pos_valid:
            return None
        return geodetic_from_ned(self.copter.estimate.pos_ned, tuple(origin))
