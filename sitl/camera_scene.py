"""What a simulated camera sees: the world's floor (or terrain), its floor markers, walls and obstacles.

Frame and units: world = LOCAL_NED at the EKF origin (x north, y east, z down), metres. The floor
is the plane z = 0 and a surface h metres above it is at z = -h (companion/world.py). A view is
given as rays in the world frame: the camera origin (3,) m and per-pixel directions (three (H, W)
float32 arrays north, east, down, any length; a zero ray meets nothing). :meth:`Scene.shade` returns the grey level (float32,
0..255) each ray meets first:

- the floor: a procedural texture from ``floor_seed`` with about equal contrast at every scale
  (noise with a 1/f amplitude spectrum from 5 mm to 2.56 m, so optic flow finds texture at any
  height), repeating every 10.24 m; texels of 5 mm, mip-mapped so that a far or grazing floor
  does not alias (:data:`FLOOR`). In a world with ``ground: terrain`` (outdoors, a fixed wing's
  forward camera at 20-150 m) the floor is terrain instead (:data:`TERRAIN`): the same kind of
  texture with 0.25 m texels and wavelengths from 0.5 m to 512 m, repeating every 512 m (so a
  pixel finds contrast from decimetres straight below to tens of metres near the horizon), mip-mapped
  down to its mean grey, drawn at any distance: the ground reaches the true horizon;
- floor markers: real ArUco markers of the world's ``marker_dictionary``, black (20) on white
  paper (235) with a quiet zone of one cell around the black square. ``size_m`` is the black
  square's side; the marker lies as :meth:`companion.world.FloorMarker.corners` places it (its
  top edge faces ``yaw_deg``, from north towards east);
- walls (their doors and windows cut out) and obstacle boxes: flat grey, from 110 for a wall
  running east-west to 160 for one running north-south, so that corners show; obstacle tops 175;
- nothing within :data:`MAX_RANGE_M` (above the walls: no ceiling is modelled): :data:`SKY_GREY`;
  over terrain, the sky above the horizon: a smooth gradient from :data:`SKY_HORIZON_GREY` to
  :data:`SKY_ZENITH_GREY` (little texture, as a real sky), and walls and obstacles at any distance.
  Floor markers are drawn within :data:`MAX_RANGE_M` (horizontally) of the camera in either case.

:meth:`Scene.trace` finds what rays meet (the renderer's pixels, the simulated laser beams) and
:meth:`Scene.cast` what one ray meets, with the surface's normal.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from companion.world import FloorMarker, Obstacle, World, aruco_dictionary

MARKER_CELLS = 4 + 2  # bits per side plus the black border, cells
QUIET_ZONE_CELLS = 1  # white paper around the black square, cells
PAPER_CELLS = MARKER_CELLS + 2 * QUIET_ZONE_CELLS  # side of the paper, cells
MARKER_TEXELS_PER_CELL = 64  # finest marker mip level
MARKER_BLACK, PAPER_WHITE = 20.0, 235.0

FLOOR_MEAN, FLOOR_STD = 128.0, 35.0  # grey levels of the floor and terrain textures (their finest level)


@dataclass(frozen=True)
class GroundTexture:
    """A periodic 1/f noise texture of the ground (see :func:`floor_pyramid`)."""

    texel_m: float  # finest mip level, metres per texel
    tile_texels: int  # the texture repeats every tile_texels * texel_m metres
    largest_m: float  # longest wavelength, metres
    levels: int  # mip levels, texels texel_m * 2**l


FLOOR = GroundTexture(0.005, 2048, 2.56, 9)  # indoors: texels 5 mm .. 1.28 m, repeating every 10.24 m
TERRAIN = GroundTexture(0.25, 2048, 512.0, 12)  # ``ground: terrain``: texels 0.25 m .. 512 m (the last: the mean)

MAX_RANGE_M = 100.0  # nothing further away is drawn (over terrain: no floor markers further away horizontally)
SKY_GREY = 90.0
SKY_HORIZON_GREY, SKY_ZENITH_GREY = 200.0, 235.0  # the sky over terrain, at the horizon and straight up
WALL_GREYS = (110.0, 160.0)  # a wall running east-west, north-south (in between: by |cos direction|)
TOP_GREY = 175.0  # obstacle tops
REMAP_WIDTH = 1024  # points per row of the maps of sample_wrapped
UP = (0.0, 0.0, -1.0)  # the normal of the floor and of the obstacle tops, NED

Rays = tuple[np.ndarray, np.ndarray, np.ndarray]  # north, east, down components, each (H, W) float32
Window = Callable[[np.ndarray], "tuple[slice, slice] | None"]  # see Scene.shade


def everywhere(corners: np.ndarray) -> tuple[slice, slice]:
    """A :data:`Window` that traces every ray, whatever the polygon's ``corners``."""
    return slice(None), slice(None)


@functools.lru_cache(maxsize=4)
def floor_pyramid(seed: int, ground: GroundTexture = FLOOR) -> tuple[np.ndarray, ...]:
    """The mip levels of the texture ``ground`` (float32 grey, periodic) from ``seed``: noise with
    a 1/f amplitude spectrum (about equal contrast at every scale) from 2 texels to
    ``ground.largest_m``, mean FLOOR_MEAN and standard deviation FLOOR_STD; level l has texels of
    ``ground.texel_m * 2**l`` metres, rows along north, columns along east."""
    n = ground.tile_texels
    rng = np.random.default_rng(seed)
    shape = (n, n // 2 + 1)
    spectrum = rng.standard_normal(shape, np.float32) + 1j * rng.standard_normal(shape, np.float32)
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(n), np.fft.rfftfreq(n), indexing="ij")).astype(np.float32)  # cycles/texel
    amplitude = np.where(f >= ground.texel_m / ground.largest_m, 1.0 / np.maximum(f, np.float32(1e-12)),
                         np.float32(0.0))
    noise = np.fft.irfft2(spectrum * amplitude, s=(n, n))  # float32 (numpy >= 2 keeps single precision)
    level = np.clip(FLOOR_MEAN + noise * (FLOOR_STD / noise.std()), 0.0, 255.0).astype(np.float32)
    levels = [level]
    for _ in range(ground.levels - 1):
        levels.append(_halve(levels[-1]))
    return tuple(levels)


def _halve(image: np.ndarray) -> np.ndarray:
    """Mean of every 2x2 block (keeps a periodic texture periodic and a cell grid aligned)."""
    h, w = image.shape[:2]
    return image.reshape(h // 2, 2, w // 2, 2, *image.shape[2:]).mean(axis=(1, 3), dtype=np.float32)


def check_marker_ids(world: World) -> World:
    """``world``, if every floor marker's id is in the world's ``marker_dictionary``; else
    ValueError naming the marker and the dictionary."""
    count = cv2.aruco.getPredefinedDictionary(aruco_dictionary(world.marker_dictionary)).bytesList.shape[0]
    for i, marker in enumerate(world.floor_markers):
        if not 0 <= marker.id < count:
            raise ValueError(f"floor_markers[{i}]: id {marker.id} is not in the simulated camera's ArUco dictionary "
                             f"{world.marker_dictionary} (ids 0-{count - 1})")
    return world


@dataclass(frozen=True)
class MarkerTexture:
    """One floor marker on its paper: mip levels of (premultiplied grey, coverage), float32
    (n, n, 2), level l with ``texel_m * 2**l`` metres per texel, columns towards the marker's
    ``right`` and rows towards its ``down`` ([north, east] unit vectors from FloorMarker.corners)."""

    marker: FloorMarker
    levels: tuple[np.ndarray, ...]
    texel_m: float  # finest level, metres per texel
    right: tuple[float, float]
    down: tuple[float, float]

    @classmethod
    def make(cls, marker: FloorMarker, dictionary_name: str) -> MarkerTexture:
        """The texture of ``marker``, drawn from the ArUco dictionary of OpenCV's name ``dictionary_name``."""
        dictionary = cv2.aruco.getPredefinedDictionary(aruco_dictionary(dictionary_name))
        k = MARKER_TEXELS_PER_CELL
        bits = cv2.aruco.generateImageMarker(dictionary, marker.id, MARKER_CELLS * k, borderBits=1)
        paper = cv2.copyMakeBorder(bits, *[QUIET_ZONE_CELLS * k] * 4, cv2.BORDER_CONSTANT, value=255)
        grey = np.where(paper > 127, PAPER_WHITE, MARKER_BLACK).astype(np.float32)
        levels = [np.dstack((grey, np.ones_like(grey)))]
        while levels[-1].shape[0] > PAPER_CELLS:
            levels.append(_halve(levels[-1]))
        top_left, top_right, _, bottom_left = marker.corners()
        right, down = ((end - top_left) / marker.size_m for end in (top_right, bottom_left))
        return cls(marker, tuple(levels), marker.size_m / (MARKER_CELLS * k),
                   (float(right[0]), float(right[1])), (float(down[0]), float(down[1])))

    def corners(self) -> np.ndarray:
        """(4, 3) corners (NED, m) of the paper on the floor: the black square's, grown by the quiet zone."""
        centre = np.array(self.marker.position)
        paper = centre + (self.marker.corners() - centre) * (PAPER_CELLS / MARKER_CELLS)
        return np.column_stack((paper, np.zeros(len(paper))))

    def sample(self, north: np.ndarray, east: np.ndarray, footprint_m: float) -> np.ndarray:
        """(grey premultiplied, coverage) (…, 2) at floor offsets north, east (m) from the
        marker's centre, from the mip level whose texels match ``footprint_m`` (m per pixel)."""
        level = int(np.clip(round(math.log2(max(footprint_m, 1e-9) / self.texel_m)), 0, len(self.levels) - 1))
        texture = self.levels[level]
        texel = self.texel_m * 2 ** level
        half = texture.shape[0] / 2.0 - 0.5  # remap samples at texel centres
        col = (self.right[0] * north + self.right[1] * east) * (1.0 / texel) + half
        row = (self.down[0] * north + self.down[1] * east) * (1.0 / texel) + half
        return cv2.remap(texture, col, row, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0))


@dataclass(frozen=True)
class WallFace:
    """A vertical wall from ``start`` to ``end`` ([x north, y east], m) whose solid parts are the
    ``pieces`` (along_from, along_to, bottom, top: metres along from ``start`` and above the floor)."""

    start: tuple[float, float]
    end: tuple[float, float]
    pieces: tuple[tuple[float, float, float, float], ...]
    grey: float

    @classmethod
    def make(cls, start: tuple[float, float], end: tuple[float, float], height_m: float,
             holes: list[tuple[float, float, float, float]]) -> WallFace:
        """A wall ``height_m`` high with rectangular ``holes`` (along_from, along_to, bottom, top)."""
        length = math.dist(start, end)
        cuts = sorted({0.0, length, *(min(max(v, 0.0), length) for h in holes for v in h[:2])})
        pieces = []
        for a, b in zip(cuts, cuts[1:]):
            spans = [(0.0, height_m)]
            for lo, hi, bottom, top in holes:
                if lo < b and hi > a:  # the hole covers this stretch: cut its heights out
                    spans = [p for z0, z1 in spans for p in ((z0, min(z1, bottom)), (max(z0, top), z1)) if p[1] > p[0]]
            pieces += [(a, b, z0, z1) for z0, z1 in spans]
        direction = math.atan2(end[1] - start[1], end[0] - start[0])
        east_west, north_south = WALL_GREYS
        return cls(start, end, tuple(pieces), east_west + (north_south - east_west) * abs(math.cos(direction)))

    @property
    def normal(self) -> tuple[float, float, float]:
        """A horizontal unit normal (NED) of the face (towards its left seen from ``start``)."""
        length = math.dist(self.start, self.end)
        return (-(self.end[1] - self.start[1]) / length, (self.end[0] - self.start[0]) / length, 0.0)

    @property
    def top_m(self) -> float:
        """Height of the highest solid part above the floor, metres."""
        return max((top for *_, top in self.pieces), default=0.0)

    def corners(self) -> np.ndarray:
        """(4, 3) corners (NED, m) of the rectangle holding every piece."""
        (ax, ay), (bx, by), z = self.start, self.end, -self.top_m
        return np.array([[ax, ay, 0.0], [bx, by, 0.0], [bx, by, z], [ax, ay, z]])

    def distance_2d(self, x: float, y: float) -> float:
        """Horizontal distance (m) from the point (north, east) to the wall's line segment."""
        (ax, ay), (bx, by) = self.start, self.end
        length2 = (bx - ax) ** 2 + (by - ay) ** 2
        w = min(max(((x - ax) * (bx - ax) + (y - ay) * (by - ay)) / length2, 0.0), 1.0)
        return math.hypot(x - ax - w * (bx - ax), y - ay - w * (by - ay))


def wall_faces(world: World) -> list[WallFace]:
    """The walls with their openings cut out, and the four sides of every obstacle."""
    faces = []
    for wall in world.walls:
        holes = []
        for opening in world.openings:
            distance, along = wall.locate(opening.center)
            if distance <= 0.01:
                half = opening.width_m / 2
                holes.append((along - half, along + half, opening.bottom_m, opening.top_m))
        faces.append(WallFace.make(wall.start, wall.end, wall.height_m, holes))
    for box in world.obstacles:
        (xa, ya), (xb, yb) = box.min, box.max
        corners = [(xa, ya), (xb, ya), (xb, yb), (xa, yb)]
        faces += [WallFace.make(p, q, box.height_m, []) for p, q in zip(corners, corners[1:] + corners[:1])]
    return faces


class Scene:
    """The world as a camera sees it (see the module docstring); one per world and floor seed."""

    def __init__(self, world: World, floor_seed: int = 0) -> None:
        self.terrain = world.ground == "terrain"
        self.ground = TERRAIN if self.terrain else FLOOR
        self.floor = floor_pyramid(floor_seed, self.ground)
        self.range_m = math.inf if self.terrain else MAX_RANGE_M  # what is further away is not drawn
        # Marker textures are made when a marker first comes within MAX_RANGE_M (each is ~2.7 MB and
        # ~25 ms to make: a world with a marker at each of 641 landmarks would take 2 GB and 17 s up
        # front), and forgotten once far behind.
        self.floor_markers = check_marker_ids(world).floor_markers
        self.marker_dictionary = world.marker_dictionary
        self._textures: dict[int, MarkerTexture] = {}
        self._marker_centres = np.array([m.position for m in self.floor_markers], float).reshape(-1, 2)
        self._marker_reach = np.array([m.size_m * PAPER_CELLS / MARKER_CELLS / math.sqrt(2.0)
                                       for m in self.floor_markers]) + MAX_RANGE_M
        self.faces = wall_faces(world)
        self.obstacles = world.obstacles
        # by surface label: 0 nothing, 1 floor (textured instead), then the faces, then the obstacle tops
        self.greys = np.array([SKY_GREY, FLOOR_MEAN, *(f.grey for f in self.faces), *[TOP_GREY] * len(self.obstacles)],
                              np.float32)
        self.normals = np.array([[math.nan] * 3, UP, *(f.normal for f in self.faces), *[UP] * len(self.obstacles)])

    @property
    def markers(self) -> list[MarkerTexture]:
        """Every floor marker's texture (makes those not made yet)."""
        return [self._texture(k) for k in range(len(self.floor_markers))]

    def markers_near(self, origin: tuple[float, ...]) -> list[MarkerTexture]:
        """The textures of the floor markers whose paper may lie within :data:`MAX_RANGE_M` of
        ``origin`` (NED, m): no other can be drawn."""
        if not self.floor_markers:
            return []
        gap = np.hypot(self._marker_centres[:, 0] - origin[0], self._marker_centres[:, 1] - origin[1])
        near = [int(k) for k in np.flatnonzero(gap <= self._marker_reach)]
        if len(self._textures) > 4 * len(near) + 64:  # forget those left far behind (a flight over many)
            self._textures = {k: self._textures[k] for k in near if k in self._textures}
        return [self._texture(k) for k in near]

    def _texture(self, k: int) -> MarkerTexture:
        if (texture := self._textures.get(k)) is None:
            texture = self._textures[k] = MarkerTexture.make(self.floor_markers[k], self.marker_dictionary)
        return texture

    def nearest_distance(self, origin: np.ndarray) -> float:
        """A lower bound of the distance (m) from ``origin`` (NED, m) to anything drawn."""
        x, y, z = (float(v) for v in origin)
        bounds = [max(-z, 0.0)]
        bounds += [math.hypot(face.distance_2d(x, y), max(-z - face.top_m, 0.0)) for face in self.faces]
        for box in self.obstacles:
            gaps = (max(box.min[0] - x, 0.0, x - box.max[0]), max(box.min[1] - y, 0.0, y - box.max[1]),
                    max(-box.height_m - z, 0.0, z))
            bounds.append(math.hypot(*gaps))
        return min(bounds)

    def shade(self, origin: np.ndarray, rays: Rays, footprint_k: np.ndarray, window: Window) -> np.ndarray:
        """The grey level (H, W) float32 that each ray from ``origin`` (NED, m) meets first.

        ``footprint_k`` (H, W) is |ray|^2 times the pixel's angular size (rad): a surface at
        distance D seen at incidence angle i covers about D * angle / cos i metres per pixel.
        ``window``: see :meth:`trace`.
        """
        o = tuple(float(v) for v in origin)
        dx, dy, dz = rays
        t_best, surface = self.trace(origin, rays, window)
        image = self.greys[surface]
        if self.terrain:
            self._shade_sky(rays, surface == 0, image)
        floor = surface == 1
        if floor.any():
            tf = np.where(floor, t_best, np.float32(0.0))
            north, east = tf * dx, tf * dy  # floor points relative to the camera, m
            footprint = np.full(dz.shape, np.float32(self.ground.texel_m))  # m per pixel (meaningless off the floor)
            np.divide(tf * footprint_k, dz, out=footprint, where=floor)
            self._shade_floor(o, north, east, footprint, floor, image)
            for marker in self.markers_near(o):
                if (win := window(marker.corners())) is not None:
                    self._shade_marker(marker, o, north[win], east[win], footprint[win], floor[win], image[win])
        return image

    def cast(self, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((N,) distances m, (N, 3) unit normals NED of the surfaces) where the rays from ``origin``
        (NED, m) along the (N, 3) unit ``directions`` (NED) first meet something; NaN where nothing
        within ``range_m`` (:data:`MAX_RANGE_M`; over terrain, any distance). Float32 distances, as the
        renderer's: 1e-7 relative."""
        d = np.asarray(directions, dtype=float).reshape(1, -1, 3)  # a one-row image of rays
        t, surface = self.trace(origin, (d[..., 0], d[..., 1], d[..., 2]), everywhere)
        return np.where(surface[0] > 0, t[0], np.nan), self.normals[surface[0]]

    def trace(self, origin: np.ndarray, rays: Rays, window: Window) -> tuple[np.ndarray, np.ndarray]:
        """(distance in ray lengths (H, W) float32, label (H, W) int16) of what each ray from
        ``origin`` (NED, m) meets first: 0 nothing (at ``range_m`` / |ray|), 1 the floor,
        then the faces (:func:`wall_faces`), then the obstacle tops (see ``greys``, ``normals``).

        ``window(corners)`` gives the image rows and columns (slices) that may show a flat convex
        polygon with (N, 3) corners (NED, m), None if it is out of view: only those are traced.
        """
        o = tuple(float(v) for v in origin)
        dx, dy, dz = rays
        with np.errstate(divide="ignore"):  # a zero ray meets nothing
            t_best = (np.float32(self.range_m) / np.sqrt(dx * dx + dy * dy + dz * dz)).astype(np.float32)  # ray lengths
        surface = np.zeros(dz.shape, np.int16)  # label of what each ray meets (see self.greys)
        if o[2] < 0:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.float32(-o[2]) / dz
            hit = (dz > 0) & (t < t_best)
            np.copyto(t_best, t, where=hit)
            surface[hit] = 1
        for k, face in enumerate(self.faces, 2):
            if (win := window(face.corners())) is not None:
                self._hit_face(face, k, o, tuple(r[win] for r in rays), t_best[win], surface[win])
        for k, box in enumerate(self.obstacles, 2 + len(self.faces)):
            (xa, ya), (xb, yb), z = box.min, box.max, -box.height_m
            if (win := window(np.array([[xa, ya, z], [xb, ya, z], [xb, yb, z], [xa, yb, z]]))) is not None:
                self._hit_top(box, k, o, tuple(r[win] for r in rays), t_best[win], surface[win])
        return t_best, surface

    @staticmethod
    def _hit_face(face: WallFace, label: int, o: tuple[float, ...], rays: Rays,
                  t_best: np.ndarray, surface: np.ndarray) -> None:
        """Give the rays that meet ``face`` before ``t_best`` (updated in place) the ``label``."""
        (ax, ay), (bx, by) = face.start, face.end
        length = math.hypot(bx - ax, by - ay)
        ux, uy = (bx - ax) / length, (by - ay) / length
        ox, oy, oz = o
        dx, dy, dz = rays
        with np.errstate(divide="ignore", invalid="ignore"):  # rays parallel to the face, zero rays: no hit
            t = np.float32(ux * (ay - oy) - uy * (ax - ox)) / (np.float32(ux) * dy - np.float32(uy) * dx)
            near = (t > 0) & (t < t_best)
            if not near.any():
                return
            along = np.float32((ox - ax) * ux + (oy - ay) * uy) + t * (np.float32(ux) * dx + np.float32(uy) * dy)
            height = -(np.float32(oz) + t * dz)
        solid = np.zeros_like(near)
        for a, b, bottom, top in face.pieces:
            solid |= (along >= a) & (along <= b) & (height >= bottom) & (height <= top)
        hit = near & solid
        np.copyto(t_best, t, where=hit)
        surface[hit] = label

    @staticmethod
    def _hit_top(box: Obstacle, label: int, o: tuple[float, ...], rays: Rays,
                 t_best: np.ndarray, surface: np.ndarray) -> None:
        """Give the rays that meet the top of ``box`` before ``t_best`` (updated in place) the ``label``."""
        ox, oy, oz = o
        if oz >= -box.height_m:
            return
        dx, dy, dz = rays
        with np.errstate(divide="ignore", invalid="ignore"):  # level rays, zero rays: no hit
            t = np.float32(-box.height_m - oz) / dz
            x, y = np.float32(ox) + t * dx, np.float32(oy) + t * dy
        hit = ((dz > 0) & (t < t_best) & (x >= box.min[0]) & (x <= box.max[0])
               & (y >= box.min[1]) & (y <= box.max[1]))
        np.copyto(t_best, t, where=hit)
        surface[hit] = label

    @staticmethod
    def _shade_sky(rays: Rays, sky: np.ndarray, image: np.ndarray) -> None:
        """Paint the ``sky`` pixels of ``image`` (in place) with the sky over terrain: grey from
        SKY_HORIZON_GREY at the horizon to SKY_ZENITH_GREY straight up, by the sine of the ray's elevation."""
        if not sky.any():
            return
        dx, dy, dz = (r[sky] for r in rays)
        with np.errstate(divide="ignore", invalid="ignore"):  # zero rays: blacked out by the camera anyway
            up = np.clip(-dz / np.sqrt(dx * dx + dy * dy + dz * dz), 0.0, 1.0)
        image[sky] = np.float32(SKY_HORIZON_GREY) + np.float32(SKY_ZENITH_GREY - SKY_HORIZON_GREY) * up

    def _shade_floor(self, o: tuple[float, ...], north: np.ndarray, east: np.ndarray, footprint: np.ndarray,
                     floor: np.ndarray, image: np.ndarray) -> None:
        """Texture the floor pixels of ``image``, each from the mip level that matches its footprint."""
        texel_m, count = self.ground.texel_m, self.ground.levels
        levels = np.log2(footprint * np.float32(1.0 / texel_m))
        levels = np.clip(np.rint(levels, out=levels), 0, count - 1, out=levels).astype(np.int8)
        levels[~floor] = -1
        # the pixels sorted by level: each level samples exactly its own pixels (a level's pixels
        # form a band across the image, whose bounding box under a roll would hold most of it)
        order = np.argsort(levels.ravel(), kind="stable")
        ends = np.cumsum(np.bincount(levels.ravel() + 1, minlength=count + 1))  # of levels -1 (not floor), 0, 1, ...
        north, east = north.ravel()[order[ends[0]:]], east.ravel()[order[ends[0]:]]
        for level, (start, end) in enumerate(zip(ends[:-1] - ends[0], ends[1:] - ends[0])):
            if start == end:
                continue
            texture = self.floor[level]
            n = texture.shape[0]
            scale = 1.0 / (texel_m * 2 ** level)  # texels per metre
            row = north[start:end] * np.float32(scale) + np.float32((o[0] * scale) % n - 0.5)  # texel centres: integers
            col = east[start:end] * np.float32(scale) + np.float32((o[1] * scale) % n - 0.5)
            np.put(image, order[ends[0] + start:ends[0] + end], sample_wrapped(texture, col, row))

    @staticmethod
    def _shade_marker(marker: MarkerTexture, o: tuple[float, ...], north: np.ndarray, east: np.ndarray,
                      footprint: np.ndarray, floor: np.ndarray, image: np.ndarray) -> None:
        """Draw ``marker`` (with its paper) over the floor pixels of ``image`` that see it (all
        arrays: the window of the image that may show it; ``image`` updated in place)."""
        if not floor.any():
            return
        centre = (np.float32(marker.marker.position[0] - o[0]), np.float32(marker.marker.position[1] - o[1]))
        sample = marker.sample(north - centre[0], east - centre[1], float(np.mean(footprint, where=floor)))
        coverage = sample[..., 1] * floor
        image *= 1.0 - coverage
        image += sample[..., 0] * floor


def sample_wrapped(texture: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """(N,) float32: the periodic ``texture`` interpolated bilinearly (cv2.remap) at the (N,) float32
    texel coordinates ``col``, ``row`` (texel centres at integers)."""
    width = min(col.size, REMAP_WIDTH)  # cv2.remap takes maps of at most 32767 a side: fold the points into rows
    rows = -(-col.size // width)
    pad = (0, rows * width - col.size)
    maps = (np.pad(c, pad).reshape(rows, width) for c in (col, row))
    return cv2.remap(texture, *maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP).ravel()[:col.size]
