"""Synthetic scans of a world and per-stage timings of the lidar pipeline (for ``companion bench``).

:class:`ArenaGeometry` is a small vectorised 3-D ray caster of a :class:`sitl.world.World`:
walls are vertical rectangles standing on the floor (doors and windows cut out), obstacles are
boxes (four sides and a top), the floor is the plane z = 0. Frames as everywhere: world
LOCAL_NED (x north, y east, z down, metres; heights above the floor are -z), body FRD, sensor
frames as in drivers/scan.py (beam angle ``a`` points along ``(cos a, sin a, 0)``).

:func:`run_stage_bench` renders a representative 1081-beam UTM-30LX scan of the default arena
(1 cm noise) and times every stage of the planar pipeline on it, plus the height fix on a
683-beam URG-04LX scan.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.frames import rotation_from_euler
from companion.nav.corners import find_corners
from companion.nav.heading import track_heading
from companion.nav.height import HeightEstimator
from companion.nav.lines import extract_lines
from companion.nav.planar import Mount2D, PlanarLocalizer
from drivers.scan import Scan
from sitl.world import World, load_world

DEFAULT_WORLD = Path(__file__).resolve().parents[2] / "config" / "worlds" / "arena.yaml"
UTM30LX_ANGLES = -(np.arange(1081) - 540) * (2 * math.pi / 1440)  # 270 deg, 0.25 deg steps
URG04LX_ANGLES = -(np.arange(683) - 341) * (2 * math.pi / 1024)  # 240 deg, 0.35 deg steps


@dataclass(frozen=True)
class ArenaGeometry:
    """The surfaces of a world for ray casting (NED metres, heights above the floor)."""

    walls: np.ndarray  # (S, 6) vertical rectangles: x0, y0, x1, y1, bottom height, top height
    tops: np.ndarray  # (T, 5) horizontal rectangles: x min, y min, x max, y max, height

    @classmethod
    def from_world(cls, world: World) -> ArenaGeometry:
        walls: list[tuple[float, ...]] = []
        for wall in world.walls:
            walls.extend(_cut_openings(wall.start, wall.end, wall.height_m, world))
        tops: list[tuple[float, ...]] = []
        for box in world.obstacles:
            (x0, y0), (x1, y1), h = box.min, box.max, box.height_m
            walls.extend([(x0, y0, x1, y0, 0.0, h), (x1, y0, x1, y1, 0.0, h),
                          (x1, y1, x0, y1, 0.0, h), (x0, y1, x0, y0, 0.0, h)])
            tops.append((x0, y0, x1, y1, h))
        return cls(np.array(walls, dtype=float).reshape(-1, 6), np.array(tops, dtype=float).reshape(-1, 5))

    def segments_at(self, height_m: float) -> np.ndarray:
        """(S, 4) wall segments [x0, y0, x1, y1] a horizontal scan at ``height_m`` above the
        floor meets (doors and windows at that height cut out, obstacle sides included): the
        ``walls`` to give PlanarLocalizer for its relocalization tie-break."""
        w = self.walls
        return w[(w[:, 4] <= height_m) & (w[:, 5] >= height_m), :4]

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Distance (m) along each unit direction (N, 3) from ``origin`` (3,) NED to the first
        surface; inf where a ray hits nothing."""
        best = self._cast_walls(origin, directions)
        dz = directions[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t_floor = np.where(dz > 1e-9, -origin[2] / dz, np.inf)
            best = np.minimum(best, np.where(t_floor > 0, t_floor, np.inf))
            for x0, y0, x1, y1, h in self.tops:
                t = (-h - origin[2]) / dz
                x = origin[0] + t * directions[:, 0]
                y = origin[1] + t * directions[:, 1]
                hit = (t > 0) & (x >= x0) & (x <= x1) & (y >= y0) & (y <= y1)
                best = np.minimum(best, np.where(hit, t, np.inf))
        return best

    def _cast_walls(self, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
        a = self.walls[:, 0:2]
        edge = self.walls[:, 2:4] - a
        to_a = a - origin[:2]  # (S, 2)
        dx, dy = directions[:, 0:1], directions[:, 1:2]  # (N, 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            denom = dx * edge[:, 1] - dy * edge[:, 0]  # (N, S)
            t = (to_a[:, 0] * edge[:, 1] - to_a[:, 1] * edge[:, 0]) / denom
            u = (to_a[:, 0] * dy - to_a[:, 1] * dx) / denom
            height = -(origin[2] + t * directions[:, 2:3])
            hit = ((t > 0) & (u >= 0) & (u <= 1) & (height >= self.walls[:, 4])
                   & (height <= self.walls[:, 5]))
        return np.where(hit, t, np.inf).min(axis=1, initial=np.inf)


def _cut_openings(start: tuple[float, float], end: tuple[float, float], height: float,
                  world: World) -> list[tuple[float, ...]]:
    """The rectangles of one wall with its doors and windows cut out."""
    sx, sy = start
    length = math.dist(start, end)
    ux, uy = (end[0] - sx) / length, (end[1] - sy) / length
    pieces: list[tuple[float, float, float, float]] = [(0.0, length, 0.0, height)]  # along0, along1, bottom, top
    for opening in world.openings:
        cx, cy = opening.center
        along = (cx - sx) * ux + (cy - sy) * uy
        if abs((cx - sx) * uy - (cy - sy) * ux) > 0.01 or not 0 <= along <= length:
            continue
        lo, hi = along - opening.width_m / 2, along + opening.width_m / 2
        cut: list[tuple[float, float, float, float]] = []
        for a0, a1, b0, b1 in pieces:
            if a1 <= lo or a0 >= hi or b1 <= opening.bottom_m or b0 >= opening.top_m:
                cut.append((a0, a1, b0, b1))
                continue
            cut += [p for p in ((a0, lo, b0, b1), (hi, a1, b0, b1),
                                (max(a0, lo), min(a1, hi), b0, opening.bottom_m),
                                (max(a0, lo), min(a1, hi), opening.top_m, b1))
                    if p[1] - p[0] > 1e-9 and p[3] - p[2] > 1e-9]
        pieces = cut
    return [(sx + a0 * ux, sy + a0 * uy, sx + a1 * ux, sy + a1 * uy, b0, b1) for a0, a1, b0, b1 in pieces]


def render_scan(geometry: ArenaGeometry, position_ned: np.ndarray, rpy: tuple[float, float, float],
                mount_position: tuple[float, float, float], mount_rpy: tuple[float, float, float],
                angles: np.ndarray, noise_m: float, rng: np.random.Generator,
                max_range_m: float = 30.0, min_range_m: float = 0.1, sequence: int = 0) -> Scan:
    """A scan from a scanner mounted at ``mount_position`` (body FRD, m) with ``mount_rpy``
    (rad) on a body at ``position_ned`` (m) with attitude ``rpy`` (roll, pitch, yaw, rad).
    Gaussian range noise of ``noise_m`` metres; beams outside [min, max] range are invalid."""
    body = rotation_from_euler(*rpy)
    sensor = body @ rotation_from_euler(*mount_rpy)
    origin = np.asarray(position_ned, dtype=float) + body @ np.asarray(mount_position, dtype=float)
    local = np.column_stack((np.cos(angles), np.sin(angles), np.zeros_like(angles)))
    ranges = geometry.cast(origin, local @ sensor.T)
    ranges = ranges + rng.normal(0.0, noise_m, ranges.shape)
    valid = np.isfinite(ranges) & (ranges >= min_range_m) & (ranges <= max_range_m)
    return Scan("bench", 0.0, angles, np.where(valid, ranges, 0.0), valid, sequence=sequence)


def run_stage_bench(repeat: int, world: World | None = None) -> dict[str, tuple[float, float]]:
    """(median ms, p99 ms) per stage over ``repeat`` calls on a representative scan: the
    default arena (or ``world``), vehicle in the south-west room at 1 m height looking north-
    east through two doors, 1081-beam UTM-30LX with 1 cm noise, mount 10 cm above the body."""
    world = world or load_world(DEFAULT_WORLD)
    geometry = ArenaGeometry.from_world(world)
    rng = np.random.default_rng(1)
    pose = (2.0, 2.0, math.radians(30.0))
    mount = Mount2D(z_m=-0.10)
    scan = render_scan(geometry, np.array([pose[0], pose[1], -1.0]), (0.0, 0.0, pose[2]),
                       (0.0, 0.0, -0.10), (0.0, 0.0, 0.0), UTM30LX_ANGLES, 0.01, rng)
    localizer = PlanarLocalizer(world.corner_array(), world.wall_angle_deg, mount=mount,
                                walls=geometry.segments_at(1.1))  # scanner 1.1 m above the floor
    points, valid, ranges = localizer.level_points(scan)
    lines = extract_lines(points, valid, localizer.params.lines, ranges)
    wall_angle = math.radians(world.wall_angle_deg)
    heading = track_heading(lines, pose[2], wall_angle, 0.0, localizer.params.heading)
    corners = find_corners(lines, localizer.params.corners)

    def planar_update() -> object:
        localizer.reset(*pose)
        return localizer.update(scan)

    vertical = render_scan(geometry, np.array([7.4, 1.6, -1.5]), (0.0, 0.0, 0.0), (0.05, 0.0, 0.05),
                           (math.pi / 2, 0.0, 0.0), URG04LX_ANGLES, 0.01, rng)
    height = HeightEstimator(mount_position=(0.05, 0.0, 0.05), mount_rpy=(math.pi / 2, 0.0, 0.0))

    def relocalize() -> object:
        localizer.forget()
        return localizer.update(scan)

    stages: dict[str, Callable[[], object]] = {
        "lidar.level_points (sensor -> levelled body)": lambda: localizer.level_points(scan),
        "lidar.lines (split-and-merge + fit)": lambda: extract_lines(points, valid, localizer.params.lines, ranges),
        "lidar.heading": lambda: track_heading(lines, pose[2], wall_angle, 0.0, localizer.params.heading),
        "lidar.corners": lambda: find_corners(lines, localizer.params.corners),
        "lidar.associate + update": lambda: localizer.match(corners, pose[:2], heading),
        "lidar.planar update (whole pipeline)": planar_update,
        "lidar.relocalize (whole pipeline, no prior)": relocalize,
        "lidar.height (vertical scan)": lambda: height.update(vertical),
    }
    return {name: _time(fn, repeat) for name, fn in stages.items()}


def _time(fn: Callable[[], object], repeat: int) -> tuple[float, float]:
    """(median ms, p99 ms) of ``fn`` over ``repeat`` calls after a short warm-up."""
    for _ in range(min(50, repeat)):
        fn()
    samples = np.empty(repeat)
    for i in range(repeat):
        start = time.perf_counter()
        fn()
        samples[i] = time.perf_counter() - start
    return float(np.median(samples) * 1e3), float(np.percentile(samples, 99) * 1e3)
