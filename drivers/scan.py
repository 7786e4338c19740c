"""The one scan type every lidar backend produces (real SCIP device, simulation, replay).

Sensor frame (like the body frame, FRD): x along the scanner's front (Hokuyo step AFRT),
y to its right, z down through its base when it stands upright. A beam at angle ``a`` points
along ``(cos a, sin a, 0)`` in that frame, so positive angles turn from the front towards the
right (clockwise seen from above). Hokuyo steps count counter-clockwise seen from above, so the
SCIP driver maps ``angle = -(step - AFRT) * 2 pi / ARES``. The mount pose in the config
(``mount.position_m``, ``mount.rpy_deg``) places this frame in the body frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Scan:
    """One sweep of a 2-D scanner."""

    sensor_id: str
    t_capture: float  # daemon monotonic clock, s: time of the first beam
    angles_rad: np.ndarray  # (N,) beam angles in the sensor frame (see module docstring)
    ranges_m: np.ndarray  # (N,) float64 metres; meaningless where not valid
    valid: np.ndarray  # (N,) bool: a real return within [min, max] range
    sweep_s: float = 0.0  # time from the first to the last beam, s (per-beam time = linear)
    sequence: int = 0  # increases by one per scan from this sensor (gaps = lost scans)

    def __post_init__(self) -> None:
        n = self.angles_rad.shape
        if self.ranges_m.shape != n or self.valid.shape != n or len(n) != 1:
            raise ValueError("angles_rad, ranges_m and valid must be 1-D arrays of one length")

    @property
    def valid_count(self) -> int:
        return int(np.count_nonzero(self.valid))

    def points(self) -> np.ndarray:
        """(M, 2) x, y of the valid returns in the sensor frame, metres, in beam order."""
        r = self.ranges_m[self.valid]
        a = self.angles_rad[self.valid]
        return np.column_stack((r * np.cos(a), r * np.sin(a)))
