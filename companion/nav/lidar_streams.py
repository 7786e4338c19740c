"""The lidar pipeline's telemetry payloads: the horizontal scan, the lines and corners extracted
from it, the map.

What an operator needs to see whether the localization is right: the scan placed on the map
with the pose the localizer fixed for it, the walls it found, which corners it saw and which
known corners its fix paired them with. Built from the pipeline's newest processed scan (which
keeps the lines, corners and fix the localizer made of it) outside the nav cycle, at
``telemetry.scan_hz``: nothing is extracted or associated again here. Payloads: docs/telemetry.md.

Frames: ``*_m`` vectors of ``lines`` and ``corners`` are in the levelled body frame (x forward,
y right, metres, rotated from the world by the yaw only); ``pose`` [x north m, y east m, yaw
rad] places that frame in the world (LOCAL_NED); ``*_ned_m`` vectors are world coordinates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.nav.corners import Corners
from companion.nav.lines import LineSet
from companion.nav.planar import PlanarFix, PlanarLocalizer
from companion.messages import Scan

STREAMS = ("scan", "lines", "corners", "map")


@dataclass(frozen=True)
class ProcessedScan:
    """The newest horizontal scan the localizer processed, as telemetry reads it (never mutated)."""

    scan: Scan
    roll: float  # body attitude the scan was levelled with, rad
    pitch: float
    fix: PlanarFix | None  # what the localizer made of it; None: no pose known (relocalizing)
    lines: LineSet  # the lines and corners the localizer found in it (sensor frame, levelled)
    corners: Corners


def scan_payloads(record: ProcessedScan, localizer: PlanarLocalizer) -> dict[str, dict[str, Any]]:
    """{stream: payload} of ``scan``, ``lines`` and ``corners`` for one processed scan."""
    scan, fix = record.scan, record.fix
    pose = None if fix is None else (fix.x, fix.y, fix.yaw)
    head = {"sensor": scan.sensor_id, "t_capture": scan.t_capture, "sequence": scan.sequence, "pose": pose}
    mount = localizer.mount
    lines, corners = record.lines, record.corners
    matched = [] if fix is None else [{"observed": i, "map_ned_m": localizer.map[j].tolist()}
                                      for i, j in fix.corner_pairs]
    return {
        "scan": {**head, "sweep_s": scan.sweep_s, "angles_rad": scan.angles_rad, "ranges_m": scan.ranges_m,
                 "valid": scan.valid, "mount": (mount.x_m, mount.y_m, mount.yaw_rad)},
        "lines": {**head, "segments_m": np.hstack((lines.start, lines.end))},
        "corners": {**head, "observed_m": corners.xy, "matched": matched,
                    "state": None if fix is None else fix.state, "fix_matched": 0 if fix is None else fix.matched},
    }


def map_payload(localizer: PlanarLocalizer) -> dict[str, Any]:
    """The map the localizer uses: wall segments at the scan height (doors and windows cut
    out), known corners, and the wall angle."""
    walls = np.zeros((0, 4)) if localizer.walls is None else localizer.walls
    return {"walls_ned_m": walls, "corners_ned_m": localizer.map, "wall_angle_deg": math.degrees(localizer.wall_angle),
            "wall_offset_deg": math.degrees(localizer.wall_offset)}
