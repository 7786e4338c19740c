"""A world: the floor plan of an indoor arena (the map a pipeline localizes in, and what the
simulator renders), or an outdoor field of point landmarks with a base, from YAML.

Frame (companion/frames.py): world = MAVLink LOCAL_NED at the EKF origin, x north, y east,
z down, metres. A world is a floor plan: every position in the file is ``[x, y]`` (north,
east) in metres, the floor is the plane z = 0, and every height (walls, obstacles, openings)
is in metres *above* the floor, so a surface ``h`` metres high is at NED z = -h.
Directions are degrees from north towards east, like yaw.

:func:`load_world` reads a file with :mod:`companion.schema`, so every error names the file,
the key path and the line. Besides the per-key checks, a world must satisfy what the
navigation pipelines rely on (the structured-arena assumptions of the two-lidar SAFMC
localization: walls at multiples of a constant angle, known corner features):

* no wall is shorter than 1 cm;
* every wall direction is ``wall_offset_deg`` plus a multiple of ``wall_angle_deg`` within
  0.1 deg (the lidar heading tracker follows the heading modulo that angle);
* every listed corner is a real corner of the map: within 1 cm of the end of one wall that
  lies on another, non-parallel wall (an L corner, or a T junction where a wall meets another);
* every opening (door, window) is centred within 1 cm of a wall, fits within its length and
  does not reach above it; a door starts at the floor, a window above it;
* walls, obstacles, floor markers, walkers (their whole footprint, along all of their path)
  and the take-off pose are inside ``bounds``, and the take-off pose is not on an obstacle.

Walkers (``walkers:``) are people walking back and forth, for the simulated scanners only: they
are not part of the map (a localizer never reads them) and the camera simulation does not draw them.
So is ``floor_relief:``, a floor that is not flat (a real building's is uneven by millimetres): the
simulated scanners see the floor at its relief, while the map, the physics and the camera keep
the plane z = 0, the datum every height is measured from.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from companion.schema import load_file, meta

ARUCO_DICTIONARY = cv2.aruco.DICT_4X4_250
"""The ArUco dictionary of the floor markers (OpenCV's named constant; its first 50 markers are
DICT_4X4_50's): the laser-dot pipeline detects them, and the simulated camera draws a world's
markers from it unless the world names another (``marker_dictionary``)."""



def aruco_dictionary(name: str) -> int:
    """OpenCV's constant of the ArUco dictionary ``name`` (e.g. "DICT_4X4_1000"); ValueError if none."""
    value = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(value, int):
        raise ValueError(f"{name!r} is not an OpenCV ArUco dictionary (e.g. DICT_4X4_1000, DICT_APRILTAG_36h11)")
    return value


TOLERANCE_M = 0.01  # how close points must be to count as coinciding / lying on a wall
ANGLE_TOLERANCE_DEG = 0.1  # how far a wall direction may be from a multiple of wall_angle_deg

_COORD_RANGE = (-1000.0, 1000.0)  # metres: anything further is a typo, not an indoor arena
_HEIGHT_RANGE = (0.01, 100.0)

Point = tuple[float, float]


def _fmt(p: Point) -> str:
    return "[" + ", ".join(f"{v:g}" for v in p) + "]"


@dataclass(frozen=True)
class Wall:
    """A straight wall segment standing on the floor, from ``start`` to ``end``.

    (The ends are not called ``from``/``to``: ``from`` is a Python keyword, and
    companion.schema maps YAML keys onto field names as they are.)
    """

    start: Point = field(metadata=meta("One end [x north, y east], metres.", _COORD_RANGE))
    end: Point = field(metadata=meta("The other end [x north, y east], metres.", _COORD_RANGE))
    height_m: float = field(default=3.0, metadata=meta(
        "Height above the floor, metres; the default 3.0 is floor to ceiling.", _HEIGHT_RANGE))

    @property
    def length_m(self) -> float:
        """Length in metres."""
        return math.dist(self.start, self.end)

    @property
    def direction_deg(self) -> float:
        """Direction from ``start`` to ``end``, degrees from north towards east, in [0, 360)."""
        return math.degrees(math.atan2(self.end[1] - self.start[1], self.end[0] - self.start[0])) % 360.0

    def locate(self, p: Point) -> tuple[float, float]:
        """(distance from ``p`` to the segment, distance along it from ``start`` to the foot of
        the perpendicular from ``p``, clamped to the segment), both in metres."""
        ax, ay = self.start
        dx, dy = self.end[0] - ax, self.end[1] - ay
        length = math.hypot(dx, dy)
        along = min(max(((p[0] - ax) * dx + (p[1] - ay) * dy) / length, 0.0), length)
        foot = (ax + dx * along / length, ay + dy * along / length)
        return math.dist(p, foot), along

    def is_parallel_to(self, other: Wall) -> bool:
        """Whether the two walls run in the same or opposite direction (within 0.1 deg)."""
        delta = (self.direction_deg - other.direction_deg) % 180.0
        return min(delta, 180.0 - delta) < ANGLE_TOLERANCE_DEG

    def validate(self) -> tuple[str, str] | None:
        if self.length_m < TOLERANCE_M:
            return "end", f"wall of zero length: end {_fmt(self.end)} is within 1 cm of start {_fmt(self.start)}"
        return None


@dataclass(frozen=True)
class FloorMarker:
    """A square fiducial (e.g. an ArUco marker) lying flat on the floor."""

    id: int = field(metadata=meta("Marker id in its dictionary (unique in the world).", (0, 99999)))
    position: Point = field(metadata=meta("Centre [x north, y east], metres.", _COORD_RANGE))
    size_m: float = field(metadata=meta("Side length of the black square, metres.", (0.01, 5)))
    yaw_deg: float = field(default=0.0, metadata=meta(
        "Direction of the marker's top edge, degrees from north towards east.", (-360, 360)))

    def corners(self) -> np.ndarray:
        """(4, 2) [x north, y east] floor corners (m) of the black square in ArUco's order: top
        left, top right, bottom right, bottom left, seen from above with the top edge up."""
        yaw = math.radians(self.yaw_deg)
        top, right = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
        half = self.size_m / 2.0
        signs = ((1, -1), (1, 1), (-1, 1), (-1, -1))  # (along top, along right)
        return np.array(self.position) + np.array([half * (a * top + b * right) for a, b in signs])


@dataclass(frozen=True)
class Landmark:
    """A point landmark outdoors (a post, a tree top, a marker board): what a landmark sensor sees.
    Its id is known to the sensor (data association is given, as in the EKF-SLAM seed)."""

    id: int = field(metadata=meta("Landmark id (unique in the world).", (0, 999999)))
    position: Point = field(metadata=meta("Where it stands [x north, y east], metres.", _COORD_RANGE))
    height_m: float = field(default=0.0, metadata=meta("Height of the point above the ground, metres.", (0, 100)))

    def ned(self) -> np.ndarray:
        """(3,) NED position, metres (z = -height)."""
        return np.array([self.position[0], self.position[1], -self.height_m])


@dataclass(frozen=True)
class Obstacle:
    """A box standing on the floor (a table, a crate): its top is a step in the floor height."""

    name: str = field(metadata=meta("Name, for logs and plots."))
    min: Point = field(metadata=meta("Corner with the smallest [x north, y east], metres.", _COORD_RANGE))
    max: Point = field(metadata=meta("Corner with the largest [x north, y east], metres.", _COORD_RANGE))
    height_m: float = field(metadata=meta("Height of the top above the floor, metres.", _HEIGHT_RANGE))

    def covers(self, x: float, y: float) -> bool:
        """Whether the point (x north, y east, metres) is on the footprint, edges included."""
        return self.min[0] <= x <= self.max[0] and self.min[1] <= y <= self.max[1]

    def validate(self) -> tuple[str, str] | None:
        if not (self.max[0] > self.min[0] and self.max[1] > self.min[1]):
            return "max", f"must exceed min {_fmt(self.min)} on both axes, got {_fmt(self.max)}"
        return None


@dataclass(frozen=True)
class Walker:
    """A person walking back and forth between ``start`` and ``end``: a vertical cylinder
    standing on the floor, there at ``speed_mps`` and back, endlessly, from ``start`` at daemon
    time 0 (a walker whose ends coincide stands still)."""

    start: Point = field(metadata=meta("Where the walk starts, at daemon time 0 [x north, y east], metres.",
                                       _COORD_RANGE))
    end: Point = field(metadata=meta("The turning point [x north, y east], metres.", _COORD_RANGE))
    speed_mps: float = field(default=1.2, metadata=meta("Walking speed, metres per second.", (0.1, 5)))
    radius_m: float = field(default=0.25, metadata=meta("Radius of the cylinder, metres.", (0.05, 2)))
    height_m: float = field(default=1.8, metadata=meta("Height of the cylinder above the floor, metres.", (0.1, 3)))

    def position_at(self, t: float | np.ndarray) -> np.ndarray:
        """Centre [x north, y east] (m) at daemon time ``t`` (s): (2,) for a scalar, (..., 2) for
        an array of times; ``start + (end - start) * tri(t * speed / length)``, where the
        triangle wave tri goes from 0 to 1 and back over two lengths of walk."""
        start = np.asarray(self.start, dtype=float)
        path = np.asarray(self.end, dtype=float) - start
        length = float(np.hypot(*path))
        if length == 0.0:
            return np.broadcast_to(start, np.shape(t) + (2,)).copy()
        phase = np.asarray(t, dtype=float) * (self.speed_mps / length) % 2.0
        return start + (1.0 - np.abs(phase - 1.0))[..., None] * path


@dataclass(frozen=True)
class FloorRelief:
    """An uneven floor: its height above the datum z = 0 is a smooth random field, the sum of
    ``WAVES`` plane waves of equal amplitude in random directions with wavelengths spread
    log-uniformly over ``wavelength_m`` .. 4 x ``wavelength_m`` and random phases, scaled so that
    its RMS over the floor is ``rms_m``. (A finished floor typically deviates by up to 4 mm under
    a 1 m straightedge and 10 mm under a 4 m one: DIN 18202, table 3.)"""

    WAVES = 24

    rms_m: float = field(metadata=meta("RMS of the floor's height about the datum (NED z = 0), metres.", (0.0, 0.1)))
    wavelength_m: float = field(default=2.0, metadata=meta(
        "Shortest wavelength of the relief, metres (the longest is four times this).", (0.1, 100.0)))
    seed: int = field(default=0, metadata=meta("Seed of the waves' directions, wavelengths and phases.", (0, 2**31)))

    @cached_property
    def _waves(self) -> tuple[np.ndarray, np.ndarray, float]:
        """(WAVES, 2) wave vectors (rad/m, north and east), (WAVES,) phases (rad), the amplitude (m)."""
        rng = np.random.default_rng(self.seed)
        heading = rng.uniform(0.0, 2.0 * math.pi, self.WAVES)
        wavelength = self.wavelength_m * 4.0 ** rng.uniform(0.0, 1.0, self.WAVES)
        vectors = (2.0 * math.pi / wavelength)[:, None] * np.column_stack((np.cos(heading), np.sin(heading)))
        return vectors, rng.uniform(0.0, 2.0 * math.pi, self.WAVES), self.rms_m * math.sqrt(2.0 / self.WAVES)

    @property
    def depth_m(self) -> float:
        """The most the floor can lie below (or above) the datum, metres: every wave's amplitude summed."""
        return self.WAVES * self._waves[2]

    def height_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Height (metres above the datum; NED z there is minus this) of the floor at the points
        (x north, y east, metres; arrays of one shape): an array of that shape."""
        vectors, phases, amplitude = self._waves
        angle = np.multiply.outer(np.asarray(x, dtype=float), vectors[:, 0])
        angle += np.multiply.outer(np.asarray(y, dtype=float), vectors[:, 1])
        angle += phases
        return amplitude * np.cos(angle).sum(axis=-1)


@dataclass(frozen=True)
class Opening:
    """A door or window: a rectangular hole in a wall, centred on the wall's line."""

    name: str = field(metadata=meta("Name, for logs and plots."))
    kind: Literal["door", "window"] = field(metadata=meta("door: from the floor up; window: above the floor."))
    center: Point = field(metadata=meta("Centre on the wall [x north, y east], metres.", _COORD_RANGE))
    width_m: float = field(metadata=meta("Width along the wall, metres.", (0.05, 100)))
    bottom_m: float = field(metadata=meta("Lower edge above the floor, metres (0 for a door).", (0, 100)))
    top_m: float = field(metadata=meta("Upper edge above the floor, metres.", _HEIGHT_RANGE))

    def validate(self) -> tuple[str, str] | None:
        if self.top_m <= self.bottom_m:
            return "top_m", f"must be above bottom_m = {self.bottom_m:g} m, got {self.top_m:g} m"
        if self.kind == "door" and self.bottom_m != 0.0:
            return "bottom_m", f"a door starts at the floor (0), got {self.bottom_m:g} m"
        if self.kind == "window" and self.bottom_m <= 0.0:
            return "bottom_m", "a window starts above the floor (> 0); use kind: door for an opening from the floor"
        return None


@dataclass(frozen=True)
class Bounds:
    """The axis-aligned rectangle the arena occupies (the geofence)."""

    min: Point = field(metadata=meta("South-west corner [x north, y east], metres.", _COORD_RANGE))
    max: Point = field(metadata=meta("North-east corner [x north, y east], metres.", _COORD_RANGE))

    def contains(self, x: float, y: float, margin: float = 0.0) -> bool:
        """Whether the point (metres) is inside, at least ``margin`` metres from the edge
        (a negative margin tolerates points that far outside)."""
        return (self.min[0] + margin <= x <= self.max[0] - margin
                and self.min[1] + margin <= y <= self.max[1] - margin)

    def validate(self) -> tuple[str, str] | None:
        if not (self.max[0] > self.min[0] and self.max[1] > self.min[1]):
            return "max", f"must exceed min {_fmt(self.min)} on both axes, got {_fmt(self.max)}"
        return None


@dataclass(frozen=True)
class World:
    """The floor plan of an arena (NED metres, heights above the floor). Load with :func:`load_world`."""

    name: str = field(metadata=meta("Name of the world, for logs and plots."))
    wall_angle_deg: Literal[90, 45, 30] = field(metadata=meta(
        "Every wall runs at a multiple of this angle (degrees, plus wall_offset_deg); the lidar tracks heading "
        "modulo it."))
    bounds: Bounds = field(metadata=meta("Rectangle holding the whole arena (the geofence)."))
    start: tuple[float, float, float] = field(metadata=meta(
        "Take-off pose on the floor: x north m, y east m, yaw deg (from north towards east).", _COORD_RANGE))
    walls: tuple[Wall, ...] = field(default=(), metadata=meta("Wall segments (none outdoors)."))
    corners: tuple[Point, ...] = field(default=(), metadata=meta(
        "Known corner features [x north, y east], metres: the map of the lidar localization."))
    floor_markers: tuple[FloorMarker, ...] = field(default=(), metadata=meta("Fiducials on the floor."))
    marker_dictionary: str = field(default="DICT_4X4_250", metadata=meta(
        "OpenCV's name of the ArUco dictionary the simulated camera draws the floor markers from (DICT_4X4_250, "
        "the laser-dot pipeline's; e.g. DICT_4X4_1000 for markers on up to 1000 landmarks, its first 250 the same)."))
    obstacles: tuple[Obstacle, ...] = field(default=(), metadata=meta("Boxes standing on the floor."))
    openings: tuple[Opening, ...] = field(default=(), metadata=meta("Doors and windows in the walls."))
    walkers: tuple[Walker, ...] = field(default=(), metadata=meta(
        "People walking back and forth, seen by simulated scanners only (not part of the map)."))
    landmarks: tuple[Landmark, ...] = field(default=(), metadata=meta(
        "Point landmarks (outdoors), seen by simulated landmark sensors; never a map a pipeline reads (the EKF-SLAM "
        "builds its own)."))
    base: Point | None = field(default=None, metadata=meta(
        "Where the vehicle's base is [x north, y east], metres (outdoors: where a return to base should end; the "
        "SITL report scores the landing against it).", _COORD_RANGE))
    wall_offset_deg: float = field(default=0.0, metadata=meta(
        "The walls run at this angle plus multiples of wall_angle_deg (degrees from north towards east): the map "
        "is in the autopilot's NED frame, and a building need not be aligned with north.", (-90.0, 90.0)))
    ground: Literal["floor", "terrain"] = field(default="floor", metadata=meta(
        "What the simulated camera draws at z = 0 (sitl/camera_scene.py). floor: an indoor floor (texture of 5 mm to "
        "2.56 m, repeating every 10.24 m), nothing beyond 100 m. terrain: open country for a camera high up (a "
        "fixed wing's forward camera at 20-150 m): texture of 0.5 m to 512 m, drawn to the horizon under a smooth "
        "sky."))
    floor_relief: FloorRelief | None = field(default=None, metadata=meta(
        "An uneven floor, for the simulated scanners only (the map, the physics and the camera keep the floor "
        "flat at z = 0); none: a flat floor."))
    survey_error_m: float = field(default=0.005, metadata=meta(
        "1-sigma error of the walls' and corners' positions as surveyed, metres: a property of this map that every "
        "lidar fix from it carries (the default: corners are accepted within 1 cm of their walls' corner).",
        (0.0, 1.0)))
    wall_direction_error_deg: float = field(default=0.0, metadata=meta(
        "1-sigma of how far the building's walls run from this map's wall directions (wall_offset_deg plus "
        "multiples of wall_angle_deg), degrees: a property of this map that every lidar heading from it carries "
        "(`companion map build` measures it; 0: the walls run exactly as drawn).", (0.0, 10.0)))

    def segments(self) -> np.ndarray:
        """Walls as an (N, 4) float array of rows [x0, y0, x1, y1], metres (NED north, east)."""
        return np.array([[*w.start, *w.end] for w in self.walls], dtype=float).reshape(-1, 4)

    def segments_at(self, height_m: float) -> np.ndarray:
        """(K, 4) float array of rows [x0, y0, x1, y1] (metres, NED north, east): what a
        horizontal scan ``height_m`` metres above the floor meets. Every wall at least that high
        contributes its pieces left once the openings it holds with ``bottom_m < height_m <
        top_m`` are cut out (a door at 1 m, a window at its sill height or above is a gap);
        lower walls are omitted. Obstacle boxes at least that high add their four sides.
        This is the ``walls`` map of :class:`companion.nav.planar.PlanarLocalizer`."""
        rows: list[tuple[float, float, float, float]] = []
        for wall in self.walls:
            if wall.height_m < height_m:
                continue
            length = wall.length_m
            holes = sorted(
                (along - o.width_m / 2, along + o.width_m / 2)
                for o in self.openings if o.bottom_m < height_m < o.top_m
                for distance, along in [wall.locate(o.center)] if distance <= TOLERANCE_M)
            (sx, sy), (ex, ey) = wall.start, wall.end

            def at(s: float) -> tuple[float, float]:  # the point s metres along (the ends exact)
                return (ex, ey) if s >= length else (sx + (ex - sx) * s / length, sy + (ey - sy) * s / length)

            s = 0.0  # start of the solid piece in progress, metres along the wall
            for lo, hi in [*holes, (length, length)]:
                if min(lo, length) > s + 1e-9:
                    rows.append((*at(s), *at(min(lo, length))))
                s = max(s, hi)
        for box in self.obstacles:
            if box.height_m >= height_m:
                (xa, ya), (xb, yb) = box.min, box.max
                rows.extend([(xa, ya, xb, ya), (xb, ya, xb, yb), (xb, yb, xa, yb), (xa, yb, xa, ya)])
        return np.array(rows, dtype=float).reshape(-1, 4)

    def corner_array(self) -> np.ndarray:
        """Corners as an (M, 2) float array of rows [x, y], metres (NED north, east)."""
        return np.array(self.corners, dtype=float).reshape(-1, 2)

    def floor_height_at(self, x: float, y: float) -> float:
        """Height (metres above the floor, >= 0) of the surface below the point (x north, y east,
        metres): the tallest obstacle whose footprint holds it, else 0.0. NED z there is minus this."""
        return max((o.height_m for o in self.obstacles if o.covers(x, y)), default=0.0)

    def is_corner(self, x: float, y: float) -> bool:
        """Whether the point (metres) is a corner of the map: within 1 cm of an end of one wall
        that lies (at an end or along it) on another wall not parallel to the first."""
        p = (x, y)
        for wall in self.walls:
            if min(math.dist(p, wall.start), math.dist(p, wall.end)) > TOLERANCE_M:
                continue
            if any(other is not wall and not other.is_parallel_to(wall)
                   and other.locate(p)[0] <= TOLERANCE_M for other in self.walls):
                return True
        return False

    def validate(self) -> tuple[str, str] | None:
        """The first broken invariant as (key path, message), e.g. ``("walls[3]", ...)``.

        companion.schema can only put such an error on a top-level key's line; load_world
        moves it to the line of the entry the key path names.
        """
        return next(self._problems(), None)

    def _problems(self) -> Iterator[tuple[str, str]]:
        for i, wall in enumerate(self.walls):
            for end in ("start", "end"):
                if not self.bounds.contains(*getattr(wall, end), margin=-TOLERANCE_M):
                    yield f"walls[{i}].{end}", f"{_fmt(getattr(wall, end))} is outside bounds"
            remainder = (wall.direction_deg - self.wall_offset_deg) % self.wall_angle_deg
            if min(remainder, self.wall_angle_deg - remainder) > ANGLE_TOLERANCE_DEG:
                yield (f"walls[{i}]", f"direction {wall.direction_deg:.2f} deg minus wall_offset_deg = "
                       f"{self.wall_offset_deg:g} is not a multiple of wall_angle_deg = {self.wall_angle_deg} "
                       f"(within {ANGLE_TOLERANCE_DEG} deg)")
        for j, corner in enumerate(self.corners):
            if not self.is_corner(*corner):
                yield (f"corners[{j}]", f"{_fmt(corner)} is not a corner of the map: no wall ends "
                       "within 1 cm of it on another, non-parallel wall")
        for k, opening in enumerate(self.openings):
            yield from self._opening_problems(f"openings[{k}]", opening)
        for k, obstacle in enumerate(self.obstacles):
            for end in ("min", "max"):
                if not self.bounds.contains(*getattr(obstacle, end)):
                    yield f"obstacles[{k}].{end}", f"{_fmt(getattr(obstacle, end))} is outside bounds"
        try:
            aruco_dictionary(self.marker_dictionary)
        except ValueError as exc:
            yield "marker_dictionary", str(exc)
        seen: set[int] = set()
        for k, marker in enumerate(self.floor_markers):
            if not self.bounds.contains(*marker.position, margin=marker.size_m / 2):
                yield f"floor_markers[{k}].position", f"marker {marker.id} does not lie inside bounds"
            if marker.id in seen:
                yield f"floor_markers[{k}].id", f"marker id {marker.id} is used twice"
            seen.add(marker.id)
        ids: set[int] = set()
        for k, landmark in enumerate(self.landmarks):
            if not self.bounds.contains(*landmark.position):
                yield f"landmarks[{k}].position", f"landmark {landmark.id} does not lie inside bounds"
            if landmark.id in ids:
                yield f"landmarks[{k}].id", f"landmark id {landmark.id} is used twice"
            ids.add(landmark.id)
        if self.base is not None and not self.bounds.contains(*self.base):
            yield "base", f"{_fmt(self.base)} is outside bounds"
        for k, walker in enumerate(self.walkers):
            for end in ("start", "end"):
                if not self.bounds.contains(*getattr(walker, end), margin=walker.radius_m):
                    yield (f"walkers[{k}].{end}", f"{_fmt(getattr(walker, end))}: a walker of radius "
                           f"{walker.radius_m:g} m there is not inside bounds")
        x, y, _ = self.start
        if not self.bounds.contains(x, y):
            yield "start", f"{_fmt((x, y))} is outside bounds"
        for obstacle in self.obstacles:
            if obstacle.covers(x, y):
                yield "start", f"{_fmt((x, y))} is on obstacle {obstacle.name!r}; take off from the floor"

    def _opening_problems(self, key: str, opening: Opening) -> Iterator[tuple[str, str]]:
        hosts = [(i, wall, wall.locate(opening.center)[1]) for i, wall in enumerate(self.walls)
                 if wall.locate(opening.center)[0] <= TOLERANCE_M]
        if not hosts:
            yield f"{key}.center", f"{_fmt(opening.center)} is not on any wall (within 1 cm)"
            return
        half = opening.width_m / 2
        fitting = [(i, wall) for i, wall, along in hosts
                   if half - TOLERANCE_M <= along <= wall.length_m - half + TOLERANCE_M]
        if not fitting:
            i, wall, _ = hosts[0]
            yield (f"{key}.width_m", f"{opening.width_m:g} m centred at {_fmt(opening.center)} does not "
                   f"fit within walls[{i}] ({_fmt(wall.start)} to {_fmt(wall.end)})")
        elif not any(opening.top_m <= wall.height_m + TOLERANCE_M for _, wall in fitting):
            i, wall = fitting[0]
            yield f"{key}.top_m", f"{opening.top_m:g} m is above walls[{i}], {wall.height_m:g} m high"


def load_world(path: str | Path) -> World:
    """Load and check the world YAML at ``path``; raises SchemaError (file, key path, line)."""
    return load_file(path, World)
