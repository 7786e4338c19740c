"""Flight log of the simulated vehicle: what the harness scores the companion against.

Everything is recorded in simulation time (s since sim start). Positions and velocities are in the
world frame (MAVLink LOCAL_NED at the EKF origin, m and m/s), Euler angles ZYX in radians, see
companion/frames.py. Non-finite numbers are written as null so the file is strict JSON.
The document layout is ``schema`` 1, described in :meth:`FlightLog.to_dict`.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Sequence
from typing import Any

SCHEMA = 1
# Indices of xx, xy, xz, yy, yz, zz in VISION_POSITION_ESTIMATE's row-major upper triangle of the
# 6x6 (x, y, z, roll, pitch, yaw) covariance.
POSITION_TRIANGLE = (0, 1, 2, 6, 7, 11)
YAW_VARIANCE = 20  # ... and of yaw-yaw, the triangle's last


def _num(value: float) -> float | None:
    """A finite float, or None for NaN/inf."""
    value = float(value)
    return value if math.isfinite(value) else None


def _vec(values: Iterable[float]) -> list[float | None]:
    """A list of finite floats (None for non-finite entries)."""
    return [_num(v) for v in values]


class FlightLog:
    """Recorder of truth, the vehicle's estimate and everything the companion sent."""

    def __init__(self, *, seed: int, lockstep: bool, monotonic_at_sim_zero: float | None) -> None:
        """``monotonic_at_sim_zero``: time.monotonic() at sim time 0 (None in lockstep)."""
        self.seed = seed
        self.lockstep = lockstep
        self.monotonic_at_sim_zero = monotonic_at_sim_zero
        self.truth: dict[str, list] = {"t": [], "pos_ned": [], "vel_ned": [], "euler_rad": []}
        self.vehicle_estimate: dict[str, list] = {"t": [], "pos_valid": [], "pos_ned": []}
        self.vision_position: dict[str, list] = {
            "t_rx": [], "usec": [], "pos_ned": [], "euler_rad": [], "reset_counter": [],
            "position_covariance": [],  # rows [xx, xy, xz, yy, yz, zz], m^2 (NaN where not sent)
            "yaw_variance": [],  # rad^2 (None where not sent)
        }
        self.vision_speed: dict[str, list] = {"t_rx": [], "usec": [], "vel_ned": []}
        self.distance_sensor: dict[str, list] = {
            "t_rx": [], "time_boot_ms": [], "id": [], "orientation": [],  # MAV_SENSOR_ROTATION
            "distance_m": [], "min_m": [], "max_m": [],
        }
        self.setpoints: dict[str, list] = {
            "t_rx": [], "frame": [], "type_mask": [], "pos": [], "vel": [], "acc": [],
        }
        self.rejected = {"nonfinite": 0, "stale_or_future": 0, "gated": 0}
        self.signing = {"unsigned_rejected": 0, "bad_signatures": 0}  # companion link, signing on
        self.origin: dict[str, float | None] = {"set_at": None, "lat": None, "lon": None, "alt": None}
        self.external_nav: dict[str, float | None] = {"first_in_use_at": None, "in_use_seconds": 0.0}
        self.modes: list[list] = []
        self.statustext: list[list] = []
        self.commands: list[list] = []

    def sample(
        self,
        t: float,
        *,
        truth_pos: Sequence[float],
        truth_vel: Sequence[float],
        truth_euler: Sequence[float],
        est_valid: bool,
        est_pos: Sequence[float],
    ) -> None:
        """One periodic (50 Hz) sample of ground truth and of the vehicle's own estimate."""
        self.truth["t"].append(t)
        self.truth["pos_ned"].append(_vec(truth_pos))
        self.truth["vel_ned"].append(_vec(truth_vel))
        self.truth["euler_rad"].append(_vec(truth_euler))
        self.vehicle_estimate["t"].append(t)
        self.vehicle_estimate["pos_valid"].append(bool(est_valid))
        self.vehicle_estimate["pos_ned"].append(_vec(est_pos))

    def add_vision_position(
        self,
        t_rx: float,
        usec: int,
        pos_ned: Sequence[float],
        euler_rad: Sequence[float],
        reset_counter: int,
        covariance: Sequence[float],
    ) -> None:
        """A VISION_POSITION_ESTIMATE as received (t_rx: sim time of reception); ``covariance``
        is the message's 21-value upper triangle (x, y, z, roll, pitch, yaw; NaN first = unknown)."""
        rec = self.vision_position
        rec["t_rx"].append(t_rx)
        rec["usec"].append(int(usec))
        rec["pos_ned"].append(_vec(pos_ned))
        rec["euler_rad"].append(_vec(euler_rad))
        rec["reset_counter"].append(int(reset_counter))
        rec["position_covariance"].append(_vec([covariance[i] for i in POSITION_TRIANGLE]))
        rec["yaw_variance"].append(_num(covariance[YAW_VARIANCE]) if math.isfinite(covariance[0]) else None)

    def add_vision_speed(self, t_rx: float, usec: int, vel_ned: Sequence[float]) -> None:
        """A VISION_SPEED_ESTIMATE as received."""
        self.vision_speed["t_rx"].append(t_rx)
        self.vision_speed["usec"].append(int(usec))
        self.vision_speed["vel_ned"].append(_vec(vel_ned))

    def add_distance_sensor(self, t_rx: float, time_boot_ms: int, sensor_id: int, orientation: int,
                            distance_cm: int, min_cm: int, max_cm: int) -> None:
        """A DISTANCE_SENSOR as received (t_rx: sim time of reception): ``time_boot_ms`` as sent (the
        companion puts its capture time there, ms on its clock, modulo 2^32), distances in cm."""
        rec = self.distance_sensor
        rec["t_rx"].append(t_rx)
        rec["time_boot_ms"].append(int(time_boot_ms))
        rec["id"].append(int(sensor_id))
        rec["orientation"].append(int(orientation))
        rec["distance_m"].append(distance_cm / 100)
        rec["min_m"].append(min_cm / 100)
        rec["max_m"].append(max_cm / 100)

    def add_setpoint(
        self,
        t_rx: float,
        frame: int,
        type_mask: int,
        pos: Sequence[float],
        vel: Sequence[float],
        acc: Sequence[float],
    ) -> None:
        """A SET_POSITION_TARGET_LOCAL_NED addressed to the vehicle."""
        rec = self.setpoints
        rec["t_rx"].append(t_rx)
        rec["frame"].append(int(frame))
        rec["type_mask"].append(int(type_mask))
        rec["pos"].append(_vec(pos))
        rec["vel"].append(_vec(vel))
        rec["acc"].append(_vec(acc))

    def add_mode(self, t: float, mode_name: str, armed: bool) -> None:
        """Mode/arming state; recorded only when it differs from the last entry."""
        entry = [t, mode_name, bool(armed)]
        if not self.modes or self.modes[-1][1:] != entry[1:]:
            self.modes.append(entry)

    def add_statustext(self, t: float, severity: int, text: str) -> None:
        """A STATUSTEXT the vehicle sent."""
        self.statustext.append([t, int(severity), text])

    def add_command(self, t: float, command: int, result: int) -> None:
        """A command handled and its MAV_RESULT."""
        self.commands.append([t, int(command), int(result)])

    def set_origin(self, t: float, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        """The EKF origin, recorded the first time it is set."""
        if self.origin["set_at"] is None:
            self.origin = {"set_at": t, "lat": float(lat_deg), "lon": float(lon_deg), "alt": float(alt_m)}

    def add_external_nav(self, t: float, in_use: bool, dt: float) -> None:
        """Whether the estimator used external navigation during the ``dt`` seconds ending at t."""
        if not in_use:
            return
        if self.external_nav["first_in_use_at"] is None:
            self.external_nav["first_in_use_at"] = t
        self.external_nav["in_use_seconds"] += dt

    def to_dict(self, sim_seconds: float) -> dict[str, Any]:
        """The log document (schema 1)."""
        return {
            "schema": SCHEMA,
            "seed": self.seed,
            "lockstep": self.lockstep,
            "sim_seconds": sim_seconds,
            "clock": {"monotonic_at_sim_zero": self.monotonic_at_sim_zero},
            "truth": self.truth,
            "vehicle_estimate": self.vehicle_estimate,
            "vision_position": self.vision_position,
            "vision_speed": self.vision_speed,
            "distance_sensor": self.distance_sensor,
            "setpoints": self.setpoints,
            "rejected": self.rejected,
            "signing": self.signing,
            "origin": self.origin,
            "external_nav": self.external_nav,
            "modes": self.modes,
            "statustext": self.statustext,
            "commands": self.commands,
        }

    def write(self, path: str, sim_seconds: float) -> None:
        """Write the log atomically (temporary file, then rename) as strict JSON."""
        tmp = f"{path}.tmp{os.getpid()}"
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(self.to_dict(sim_seconds), f, allow_nan=False, separators=(",", ":"))
        os.replace(tmp, path)
