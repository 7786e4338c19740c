"""Synthetic scans of a world and per-stage timings of the lidar pipeline (for ``companion bench``).

:func:`synthetic_scan` renders a scan with the simulator's ray caster (:mod:`sitl.raycast`):
the beams of a :mod:`drivers.lidar_models` model, placed on the body by a
:class:`drivers.mount.Mount`, with Gaussian range noise of a given sigma (the nav tests use it
too). Frames as everywhere: world LOCAL_NED (x north, y east, z down, metres; heights above
the floor are -z), body FRD, sensor frames as in companion/messages.py.

:func:`run_stage_bench` renders a representative 1081-beam UTM-30LX scan of the default arena
(1 cm noise) and times every stage of the planar pipeline on it, plus the height fix on a
682-beam URG-04LX scan.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from companion.frames import quat_from_euler, rotation_from_euler
from companion.nav.corners import find_corners
from companion.nav.heading import track_heading
from companion.nav.height import HeightEstimator
from companion.nav.lines import extract_lines
from companion.nav.planar import Mount2D, PlanarLocalizer
from companion.timing import time_stage
from drivers.lidar_models import URG_04LX, UTM_30LX, LidarModel
from drivers.mount import Mount, beam_directions
from companion.messages import Scan
from sitl.raycast import WorldGeometry, cast
from companion.world import World, load_world

DEFAULT_WORLD = Path(__file__).resolve().parents[2] / "config" / "worlds" / "arena.yaml"


def synthetic_scan(geometry: WorldGeometry, model: LidarModel, mount: Mount, position_ned: np.ndarray,
                   rpy: tuple[float, float, float], rng: np.random.Generator, noise_m: float,
                   sequence: int = 0) -> Scan:
    """A ``model`` scan from a scanner on ``mount`` on a body at ``position_ned`` (m) with
    attitude ``rpy`` (roll, pitch, yaw, rad), ray cast into ``geometry``. Gaussian range noise
    of sigma ``noise_m`` metres (unclipped, drawn from ``rng``); beams that hit nothing or fall
    outside the model's [min, max] range are invalid (range 0)."""
    angles = model.angles_rad()
    rotation, origin = mount.sensor_to_world(np.asarray(position_ned, dtype=float), quat_from_euler(*rpy))
    ranges = cast(geometry, origin, beam_directions(angles) @ rotation.T)
    ranges = ranges + rng.normal(0.0, noise_m, ranges.shape)
    valid = np.isfinite(ranges) & (ranges >= model.min_range_m) & (ranges <= model.max_range_m)
    return Scan("bench", 0.0, angles, np.where(valid, ranges, 0.0), valid, sequence=sequence)


def make_mount(position_m: tuple[float, float, float], rpy_rad: tuple[float, float, float]) -> Mount:
    """The :class:`Mount` of a sensor at ``position_m`` (body FRD, m) turned by ``rpy_rad``
    (roll, pitch, yaw, rad) relative to the body."""
    return Mount(rotation_from_euler(*rpy_rad), np.array(position_m, dtype=float))


def run_stage_bench(repeat: int, world: World | None = None) -> dict[str, tuple[float, float]]:
    """(median ms, p99 ms) per stage over ``repeat`` calls on a representative scan: the
    default arena (or ``world``), vehicle in the south-west room at 1 m height looking north-
    east through two doors, 1081-beam UTM-30LX with 1 cm noise, mount 10 cm above the body."""
    world = world or load_world(DEFAULT_WORLD)
    geometry = WorldGeometry.from_world(world)
    rng = np.random.default_rng(1)
    pose = (2.0, 2.0, math.radians(30.0))
    mount = Mount2D(z_m=-0.10)
    scan = synthetic_scan(geometry, UTM_30LX, make_mount((0.0, 0.0, -0.10), (0.0, 0.0, 0.0)),
                          np.array([pose[0], pose[1], -1.0]), (0.0, 0.0, pose[2]), rng, 0.01)
    localizer = PlanarLocalizer(world.corner_array(), world.wall_angle_deg, mount=mount,
                                walls=world.segments_at(1.1))  # scanner 1.1 m above the floor
    points, valid, ranges = localizer.level_points(scan)
    lines = extract_lines(points, valid, localizer.params.lines, ranges)
    wall_angle = math.radians(world.wall_angle_deg)
    heading = track_heading(lines, pose[2], wall_angle, 0.0, localizer.params.heading)
    corners = find_corners(lines, localizer.params.corners)

    def planar_update() -> object:
        localizer.reset(*pose)
        return localizer.update(scan)

    vertical = synthetic_scan(geometry, URG_04LX, make_mount((0.05, 0.0, 0.05), (math.pi / 2, 0.0, 0.0)),
                              np.array([7.4, 1.6, -1.5]), (0.0, 0.0, 0.0), rng, 0.01)
    height = HeightEstimator(mount_position=(0.05, 0.0, 0.05), mount_rpy=(math.pi / 2, 0.0, 0.0))

    def relocalize() -> object:
        localizer.forget()
        return localizer.update(scan)

    tiled_corners, tiled_walls = tiled_map(world, 10, 1.1)
    large = PlanarLocalizer(tiled_corners, world.wall_angle_deg, mount=mount, walls=tiled_walls)

    def relocalize_large() -> object:
        large.forget()
        return large.update(scan)

    stages: dict[str, Callable[[], object]] = {
        "lidar.level_points (sensor -> levelled body)": lambda: localizer.level_points(scan),
        "lidar.lines (split-and-merge + fit)": lambda: extract_lines(points, valid, localizer.params.lines, ranges),
        "lidar.heading": lambda: track_heading(lines, pose[2], wall_angle, 0.0, localizer.params.heading),
        "lidar.corners": lambda: find_corners(lines, localizer.params.corners),
        "lidar.associate + update": lambda: localizer.match(lines, corners, pose[:2], heading),
        "lidar.planar update (whole pipeline)": planar_update,
        "lidar.relocalize (whole pipeline, no prior)": relocalize,
        "lidar.height (vertical scan)": lambda: height.update(vertical),
    }
    timings = {name: time_stage(fn, repeat) for name, fn in stages.items()}
    # ~0.1 s a call: a few dozen calls give a stable median.
    timings["lidar.relocalize, 1,500 corners (arena tiled 10x10)"] = time_stage(relocalize_large, min(repeat, 30))
    return timings


def tiled_map(world: World, n: int, scan_height_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(corners (M, 2), walls (S, 4) at ``scan_height_m``) of ``world`` repeated n x n times at
    the pitch of its bounds (NED metres): a large map of look-alike rooms."""
    pitch = np.array(world.bounds.max) - np.array(world.bounds.min)
    shifts = np.array([(pitch[0] * i, pitch[1] * j) for i in range(n) for j in range(n)])
    corners = (world.corner_array()[None] + shifts[:, None]).reshape(-1, 2)
    walls = (world.segments_at(scan_height_m)[None] + np.tile(shifts, 2)[:, None]).reshape(-1, 4)
    return corners, walls
