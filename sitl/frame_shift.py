"""Move a run's frame so that the EKF origin lies under the vehicle's take-off point.

ArduPilot 4.0's EKF2 starts with its position at the origin and never resets it to external
navigation (NavEKF2_core::ResetPosition only takes external-navigation data younger than 250 ms,
and its fusion horizon is 250 ms behind): a vehicle that boots metres away from the origin
first goes through a long, badly damped transient. Seen with ArduCopter 4.0.5 SITL fed perfect
positions 1.4 m from the origin: EKF position swinging by 4 m and tilt by 6 degrees while
standing on the floor; started at the origin, the same EKF stays within 3 cm.

For ArduPilot SITL runs the harness therefore puts the origin at the take-off point and writes
the world, the map, the mission and the config's positions in that frame: every horizontal
coordinate minus the take-off position (headings and heights unchanged). Errors, distances and
tracking are the same in either frame; the daemon sees one consistent frame.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from companion.config import Config
from companion.frames import geodetic_from_ned
from companion.world import load_world

Offset = tuple[float, float]  # metres added to every (north, east)


def shifted(point: Any, offset: Offset) -> list[float]:
    """``point`` ([x, y] or [x, y, third]) with ``offset`` added to x and y."""
    values = [float(v) for v in point]
    values[0] += offset[0]
    values[1] += offset[1]
    return values


def shift_world(raw: dict, offset: Offset) -> dict:
    """A world YAML document (companion/world.py) with every horizontal position moved by ``offset``."""
    out = dict(raw)
    out["bounds"] = {key: shifted(raw["bounds"][key], offset) for key in ("min", "max")}
    out["start"] = shifted(raw["start"], offset)
    out["walls"] = [{**w, "start": shifted(w["start"], offset), "end": shifted(w["end"], offset)}
                    for w in raw.get("walls") or []]
    out["corners"] = [shifted(c, offset) for c in raw.get("corners") or []]
    out["openings"] = [{**o, "center": shifted(o["center"], offset)} for o in raw.get("openings") or []]
    out["obstacles"] = [{**o, "min": shifted(o["min"], offset), "max": shifted(o["max"], offset)}
                        for o in raw.get("obstacles") or []]
    out["floor_markers"] = [{**m, "position": shifted(m["position"], offset)} for m in raw.get("floor_markers") or []]
    out["walkers"] = [{**w, "start": shifted(w["start"], offset), "end": shifted(w["end"], offset)}
                      for w in raw.get("walkers") or []]
    out["landmarks"] = [{**m, "position": shifted(m["position"], offset)} for m in raw.get("landmarks") or []]
    if raw.get("base") is not None:
        out["base"] = shifted(raw["base"], offset)
    return out


def shift_mission(raw: dict, offset: Offset) -> dict:
    """A mission YAML document with every waypoint moved by ``offset``."""
    steps = []
    for step in raw.get("steps") or []:
        fly = step.get("fly") if isinstance(step, dict) else None
        if fly is not None:
            waypoints = [{**w, "position": shifted(w["position"], offset)} for w in fly.get("waypoints") or []]
            step = {**step, "fly": {**fly, "waypoints": waypoints}}
        steps.append(step)
    return {**raw, "steps": steps}


def takeoff_pose(cfg: Config) -> tuple[float, float, float]:
    """Where the vehicle of ``cfg`` starts: (north m, east m, yaw deg), ``sitl.start``, else the world's start."""
    start = cfg.sitl.start if cfg.sitl.start is not None else load_world(cfg.resolve(cfg.sitl.world)).start
    north, east, yaw_deg = (float(v) for v in start)
    return north, east, yaw_deg


def moved_origin(origin: tuple[float, float, float], takeoff: Offset) -> tuple[float, float, float]:
    """(lat, lon, alt) of the point ``takeoff`` (north, east metres) of the frame at ``origin``."""
    lat, lon, alt = geodetic_from_ned(np.array([takeoff[0], takeoff[1], 0.0]), origin)
    return float(lat), float(lon), float(alt)


def write_shifted(source: Path, target: Path, offset: Offset, shift: Any) -> Path:
    """``shift(yaml of source, offset)`` written to ``target`` (``target`` returned)."""
    target.write_text(yaml.safe_dump(shift(yaml.safe_load(source.read_text()), offset), sort_keys=False))
    return target
