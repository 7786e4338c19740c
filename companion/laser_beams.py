"""The laser beam rig: three beams fixed to the body, shooting at the floor.

Frames and units: body FRD (x forward, y right, z down), metres; world LOCAL_NED (the floor is
the plane z = 0, companion/world.py). A beam is a ray ``origin_m + l * direction`` (l >= 0, m)
in the body frame; its dot is where that ray meets the floor.

The seed's rig (its Fig. 1): three beams from the body origin, the same angle alpha between
every pair. :func:`nominal_rig` builds it symmetric about body +z (down): beam i points at
azimuth ``azimuth_deg + 120 * i`` degrees (from body +x towards +y) and tilts theta from +z
with cos(alpha) = (3 cos^2 theta - 1) / 2 (alpha = 90 deg: theta = 54.74 deg). A real rig is
never exactly that: :class:`BeamRigConfig` takes calibrated origins and directions instead
(from ``companion laser-dots calibrate``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.schema import meta

BEAMS = 3
MIN_ANGLE_DEG, MAX_ANGLE_DEG = 10.0, 119.0  # the seed's alpha in (0, 120) deg: beyond, a beam points up


@dataclass(frozen=True)
class BeamRig:
    """Three beams in body FRD: ``origins`` (3, 3) m and unit ``directions`` (3, 3), row i = beam i."""

    origins: np.ndarray
    directions: np.ndarray

    def __post_init__(self) -> None:
        origins = np.asarray(self.origins, dtype=float).reshape(BEAMS, 3)
        directions = np.asarray(self.directions, dtype=float).reshape(BEAMS, 3)
        norms = np.linalg.norm(directions, axis=1)
        if not (np.all(np.isfinite(origins)) and np.all(np.isfinite(directions)) and np.all(norms > 1e-9)):
            raise ValueError("beam origins and directions must be finite, directions non-zero")
        object.__setattr__(self, "origins", origins)
        object.__setattr__(self, "directions", directions / norms[:, None])

    def angle_deg(self, i: int, j: int) -> float:
        """Angle between beams i and j, degrees."""
        c = float(np.clip(self.directions[i] @ self.directions[j], -1.0, 1.0))
        return math.degrees(math.acos(c))

    def mean_angle_deg(self) -> float:
        """The mean angle between the three pairs of beams, degrees (the seed's alpha)."""
        return (self.angle_deg(0, 1) + self.angle_deg(1, 2) + self.angle_deg(0, 2)) / 3.0

    def floor_hits(self, rotation: np.ndarray, position_ned: np.ndarray,
                   floor_z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Where the beams meet the plane z = ``floor_z`` (NED, m) for a body at ``position_ned``
        (m) with ``rotation`` (body FRD -> NED): ((3, 3) NED points, (3,) beam lengths m). A beam
        that does not point down towards the plane gets NaN."""
        origins = position_ned + self.origins @ rotation.T
        directions = self.directions @ rotation.T
        with np.errstate(divide="ignore", invalid="ignore"):
            lengths = (floor_z - origins[:, 2]) / directions[:, 2]
        lengths = np.where((directions[:, 2] > 1e-9) & (lengths > 0), lengths, np.nan)
        return origins + lengths[:, None] * directions, lengths


def nominal_rig(angle_deg: float = 90.0, azimuth_deg: float = 0.0,
                origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> BeamRig:
    """The seed's symmetric rig: ``angle_deg`` between every pair of beams, all from ``origin_m``
    (body FRD, m), beam 0 at azimuth ``azimuth_deg`` (from body +x towards +y), beams 1 and 2 at
    +120 and +240 degrees (see the module docstring)."""
    if not MIN_ANGLE_DEG <= angle_deg <= MAX_ANGLE_DEG:
        raise ValueError(f"the angle between beams must be within [{MIN_ANGLE_DEG}, {MAX_ANGLE_DEG}] deg")
    cos_tilt = math.sqrt((2.0 * math.cos(math.radians(angle_deg)) + 1.0) / 3.0)
    sin_tilt = math.sqrt(1.0 - cos_tilt * cos_tilt)
    azimuths = np.radians(azimuth_deg + 120.0 * np.arange(BEAMS))
    directions = np.column_stack((sin_tilt * np.cos(azimuths), sin_tilt * np.sin(azimuths),
                                  np.full(BEAMS, cos_tilt)))
    return BeamRig(np.tile(np.asarray(origin_m, dtype=float), (BEAMS, 1)), directions)


@dataclass(frozen=True)
class BeamRigConfig:
    """The beam rig of a config (a companion.schema dataclass): nominal (``angle_deg``,
    ``azimuth_deg``, ``origin_m``) unless ``origins_m`` and ``directions`` (calibrated) are given."""

    angle_deg: float = field(default=90.0, metadata=meta(
        "Nominal angle between every pair of beams, degrees (the seed's alpha).", (MIN_ANGLE_DEG, MAX_ANGLE_DEG)))
    azimuth_deg: float = field(default=0.0, metadata=meta(
        "Azimuth of beam 0 from body +x towards +y, degrees; beams 1 and 2 follow at +120 and +240.", (-360, 360)))
    origin_m: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=meta(
        "Common origin of the nominal beams, body FRD, metres.", (-5, 5)))
    origins_m: list[tuple[float, float, float]] | None = field(default=None, metadata=meta(
        "Calibrated origin of each beam, body FRD, metres (three rows); null = origin_m."))
    directions: list[tuple[float, float, float]] | None = field(default=None, metadata=meta(
        "Calibrated direction of each beam, body FRD (three rows, normalised on load); null = nominal."))

    def validate(self) -> tuple[str, str] | None:
        for key in ("origins_m", "directions"):
            rows = getattr(self, key)
            if rows is not None and len(rows) != BEAMS:
                return key, f"give {BEAMS} rows, one per beam, got {len(rows)}"
        for key in ("origins_m", "directions"):
            rows = getattr(self, key) or []
            if not all(math.isfinite(v) and abs(v) <= 100.0 for row in rows for v in row):
                return key, "every value must be finite and within [-100, 100]"
        if self.directions is not None and any(math.hypot(*row) < 1e-6 for row in self.directions):
            return "directions", "a direction must not be zero"
        if self.directions is not None and any(row[2] <= 0 for row in self.directions):
            return "directions", "every beam must point down (body +z component > 0)"
        return None

    def rig(self) -> BeamRig:
        """The rig this section describes."""
        nominal = nominal_rig(self.angle_deg, self.azimuth_deg, self.origin_m)
        origins = nominal.origins if self.origins_m is None else np.array(self.origins_m, dtype=float)
        directions = nominal.directions if self.directions is None else np.array(self.directions, dtype=float)
        return BeamRig(origins, directions)
