"""`companion map build`: a lidar map from a log, written as a world YAML.

Reads the log (drivers/lidar_replay.py), builds the map (companion/nav/map_build.py) and writes
it in the world format (companion/world.py) that ``pipelines.lidar.map`` names, then loads it
back, so a map the daemon would refuse is never left behind.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import yaml

from companion.nav.map_build import BuiltMap, MapBuildParams, build_map
from companion.nav.scan_poses import scan_poses
from companion.world import load_world

BOUNDS_MARGIN_M = 1.0
LOG_POSES = "the log's own poses"
MATCHED_POSES = "scan matching (companion/nav/scan_poses.py; the map frame at the first scan, no loop closure)"


def build_map_file(log: str | Path, log_format: str, out: str | Path, wall_angle_deg: int = 90,
                   laser: str = "front", scan_topic: str | None = None,
                   pose_topic: str | None = None) -> tuple[BuiltMap, str]:
    """Build the map of ``log`` and write it to ``out``; (the map, where its poses came from).

    The scans are placed with the log's reference poses where it has them (a CARMEN log, a ROS
    bag with a pose topic); a log without any (a BreezySLAM or npz recording, a bag without a pose
    topic: a scanner carried through the building) is placed by scan matching. ValueError for a
    log it cannot use (``laser``, ``scan_topic``, ``pose_topic``: :func:`companion.replay.read_log`)."""
    from companion.replay import read_log

    scans = read_log(log, log_format, laser, scan_topic, pose_topic)
    if not scans:
        raise ValueError(f"{log}: no scan")
    posed = [(s.points(), s.valid, s.reference) for s in scans if s.reference is not None]
    source = LOG_POSES
    if not posed:
        poses = scan_poses((s.points(), s.valid) for s in scans)
        posed = [(s.points(), s.valid, (float(x), float(y), float(yaw))) for s, (x, y, yaw) in zip(scans, poses)]
        source = MATCHED_POSES
    built = build_map(posed, MapBuildParams(wall_angle_deg=wall_angle_deg))
    x, y, yaw = posed[0][2]
    out = Path(out)
    draft = out.with_name(f".{out.name}.draft")
    try:
        write_world(built, draft, Path(log).name, (x, y, math.degrees(yaw)), source)
        load_world(draft)  # the daemon's own checks: a map it would refuse raises here (SchemaError names the key)
        draft.replace(out)
    finally:
        draft.unlink(missing_ok=True)
    return built, source


def write_world(built: BuiltMap, path: str | Path, source: str, start: tuple[float, float, float],
                poses: str = LOG_POSES) -> None:
    """``built`` as a world YAML at ``path`` (``start``: take-off pose x m, y m, yaw deg; ``poses``:
    where the scans' poses came from, for the header)."""
    lo = np.minimum(built.walls[:, 0:2], built.walls[:, 2:4]).min(axis=0) - BOUNDS_MARGIN_M
    hi = np.maximum(built.walls[:, 0:2], built.walls[:, 2:4]).max(axis=0) + BOUNDS_MARGIN_M

    def point(p: np.ndarray | tuple[float, float]) -> list[float]:
        return [round(float(p[0]), 4), round(float(p[1]), 4)]

    world = {
        "name": Path(source).stem,
        "wall_angle_deg": built.wall_angle_deg,
        "wall_offset_deg": round(built.wall_offset_deg, 4),
        "survey_error_m": round(built.survey_error_m, 4),
        "wall_direction_error_deg": round(built.wall_direction_error_deg, 3),
        "bounds": {"min": point(lo), "max": point(hi)},
        "start": [round(float(v), 4) for v in start],
        "walls": [{"start": point(w[0:2]), "end": point(w[2:4])} for w in built.walls],
        "corners": [point(c) for c in built.corners],
    }
    header = (f"# Built by `companion map build` from {source}: {len(built.walls)} walls (each seen in at least "
              f"{int(built.observations.min())} scan lines), {len(built.corners)} corners; scans placed by {poses}.\n"
              "# Frame: the log's map frame as NED (x north, y east, metres; directions from north towards east).\n"
              "# survey_error_m is the spread of the scan lines about their walls (scan noise and pose error\n"
              "# included), wall_direction_error_deg the spread of the walls' directions about the wall angle.\n"
              "# Check the map on the dashboard before flying on it.\n")
    Path(path).write_text(header + yaml.safe_dump(world, sort_keys=False, default_flow_style=None))
