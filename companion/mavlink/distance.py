"""Range estimates to the autopilot as DISTANCE_SENSOR (e.g. a pipeline's height above ground,
for ArduPilot's rangefinder with RNGFND1_TYPE = 10, MAVLink).

Fields: distances in centimetres (uint16), ``orientation`` MAV_SENSOR_ROTATION_PITCH_270 for
"down", PITCH_90 for "up", NONE for "forward"; ``covariance`` the variance in cm^2 (uint8, 255 =
unknown or too large). A non-finite or out-of-span distance is never sent (counted).
"""

from __future__ import annotations

import math

from companion.mavlink.link import MavlinkLink, mavlink
from companion.messages import RangeEstimate

ORIENTATION = {"down": mavlink.MAV_SENSOR_ROTATION_PITCH_270, "up": mavlink.MAV_SENSOR_ROTATION_PITCH_90,
               "forward": mavlink.MAV_SENSOR_ROTATION_NONE}
UNKNOWN_COVARIANCE = 255


class DistanceSender:
    """Sends each pipeline's range estimates; one DISTANCE_SENSOR ``id`` per source."""

    def __init__(self, link: MavlinkLink) -> None:
        self.link = link
        self.sent = 0
        self.dropped = 0  # non-finite, or outside the span the autopilot was told
        self._ids: dict[str, int] = {}

    def submit(self, estimate: RangeEstimate) -> None:
        d, var = estimate.distance_m, estimate.variance_m2
        if not (math.isfinite(d) and math.isfinite(var) and estimate.min_m <= d <= estimate.max_m):
            self.dropped += 1
            return
        sensor_id = self._ids.setdefault(estimate.source, len(self._ids))
        covariance = min(UNKNOWN_COVARIANCE - 1, round(var * 1e4)) if var >= 0 else UNKNOWN_COVARIANCE
        self.link.send(mavlink.MAVLink_distance_sensor_message(
            int(estimate.t_capture * 1e3) & 0xFFFFFFFF, round(estimate.min_m * 100), round(estimate.max_m * 100),
            round(d * 100), mavlink.MAV_DISTANCE_SENSOR_LASER, sensor_id, ORIENTATION[estimate.orientation],
            covariance))
        self.sent += 1
