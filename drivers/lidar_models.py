"""The Hokuyo scanner models as data: beam geometry, timing, range limits and range noise.

Numbers from the SCIP 2.0 ``PP`` replies and the datasheets (/work/shared/REFERENCE.md,
"Hokuyo SCIP 2.0"). The PP reply (``pp``) is the one source of the step geometry, the scan
rate and DMIN; the SCIP emulator answers PP with the same values. A model measures steps ``amin .. amax`` of ``ares`` steps per turn; step
``afrt`` is the scanner's front. Angles are in the sensor frame of :mod:`companion.messages`
(positive from the front towards the right, i.e. clockwise seen from above), and Hokuyo steps
count counter-clockwise, so ``angle = -(step - afrt) * 2 pi / ares``: the first step is on
the scanner's right, the last on its left.

Range noise: the datasheets give an accuracy *bound* (UTM-30LX +/-30 mm from 0.1 to 10 m and
+/-50 mm from 10 to 30 m; URG-04LX +/-10 mm up to 1 m and +/-1 % of the range beyond). We
treat that bound as 3 sigma of a Gaussian and clip the noise at the bound, so a simulated
range never leaves the datasheet accuracy: sigma = 10 mm (UTM-30LX up to 10 m), 16.7 mm
(UTM-30LX beyond 10 m), 3.3 mm (URG-04LX up to 1 m), 0.33 % of the range (URG-04LX beyond).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.scip import SensorParams


@dataclass(frozen=True)
class LidarModel:
    """One scanner model. Distances in metres, times in seconds, steps in Hokuyo step units."""

    name: str
    pp: SensorParams  # the device's PP reply: steps AMIN..AMAX, AFRT, ARES, SCAN rpm, DMIN, DMAX
    max_range_m: float  # the longest range simulated (the datasheet's, which may be below DMAX)
    near_limit_m: float  # accuracy bound changes at this range
    near_bound_m: float  # accuracy bound (m) up to near_limit_m
    far_bound_m: float  # beyond near_limit_m the bound is far_bound_m + far_bound_fraction * range
    far_bound_fraction: float

    @property
    def amin(self) -> int:
        """First measured step."""
        return self.pp.amin

    @property
    def amax(self) -> int:
        """Last measured step."""
        return self.pp.amax

    @property
    def afrt(self) -> int:
        """Step pointing along the scanner's front (sensor x)."""
        return self.pp.afrt

    @property
    def ares(self) -> int:
        """Steps per full turn."""
        return self.pp.ares

    @property
    def scan_period_s(self) -> float:
        """One turn of the mirror = one scan, s."""
        return self.pp.scan_period_s

    @property
    def min_range_m(self) -> float:
        """DMIN: shorter readings are error codes, m."""
        return self.pp.dmin_mm / 1000.0

    @property
    def beams(self) -> int:
        """Number of beams per scan (steps amin .. amax inclusive)."""
        return self.amax - self.amin + 1

    @property
    def step_rad(self) -> float:
        """Angle between neighbouring beams, radians."""
        return self.pp.step_rad

    @property
    def sweep_s(self) -> float:
        """Time from the first to the last beam of a scan, s (the mirror turns at a constant rate)."""
        return self.scan_period_s * (self.amax - self.amin) / self.ares

    def angles_rad(self) -> np.ndarray:
        """(beams,) beam angles in the sensor frame, radians, in step order (right to left)."""
        return self.pp.angle_rad(np.arange(self.amin, self.amax + 1, dtype=float))

    def accuracy_bound_m(self, ranges_m: np.ndarray) -> np.ndarray:
        """Datasheet accuracy bound (m) at each range (m): the clip limit of the simulated noise."""
        far = self.far_bound_m + self.far_bound_fraction * ranges_m
        return np.where(ranges_m <= self.near_limit_m, self.near_bound_m, far)

    def range_sigma_m(self, ranges_m: np.ndarray) -> np.ndarray:
        """Standard deviation (m) of the simulated range noise at each range (m): bound / 3."""
        return self.accuracy_bound_m(ranges_m) / 3.0


UTM_30LX = LidarModel(
    name="UTM-30LX", pp=SensorParams("UTM-30LX", 23, 60000, 1440, 0, 1080, 540, 2400),
    # DMAX in the PP reply is 60 m, but ranges are specified (and accurate) to 30 m only.
    max_range_m=30.0,
    near_limit_m=10.0, near_bound_m=0.030, far_bound_m=0.050, far_bound_fraction=0.0,
)

URG_04LX = LidarModel(
    name="URG-04LX", pp=SensorParams("URG-04LX(Hokuyo Automatic Co., Ltd.)", 20, 5600, 1024, 44, 725, 384, 600),
    # Rated to 4 m; the device reports up to DMAX = 5.6 m (the real recording has 5.58 m).
    max_range_m=5.6,
    near_limit_m=1.0, near_bound_m=0.010, far_bound_m=0.0, far_bound_fraction=0.01,
)

MODELS: dict[str, LidarModel] = {m.name: m for m in (UTM_30LX, URG_04LX)}  # by name, as in the config

