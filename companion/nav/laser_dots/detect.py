"""The laser dots in a colour image: where each beam's dot is, to a tenth of a pixel, and which
beam made it.

Frames and units: pixels (u, v) = (column, row), integer values at pixel centres (OpenCV);
OpenCV's optical frame (x right, y down, z along the axis, companion/calibration.py); body FRD,
metres (the beams, companion/laser_beams.py, and the camera centre).

Steps:

1. red dominance ``R - max(G, B)`` per pixel, clipped at 0 (OpenCV's saturating uint8
   subtraction: no wrap-around), so grey, white and black surfaces give ~0 and a laser dot a
   bright blob; a saturated dot core (R = 255 and G, B raised by the sensor's crosstalk) is weaker
   than its rim, which leaves the centroid of the symmetric spot where it was;
2. pixels above ``DotParams.min_dominance``, their 8-connected components, kept by area;
3. each blob's centroid weighted by its dominance values (sub-pixel);
4. identity by structured light: the camera and the beams are fixed to the body, so the dot of
   beam i can only appear on one fixed image curve, the projection of ``origin_i + l d_i`` for
   lengths l in ``length_range_m`` (through the lens distortion). Each beam takes the blob
   nearest its curve, all three chosen together (brute force over the few candidates): most
   beams assigned first, then the least summed cost, where the cost is the distance from the
   curve plus ``prior_weight`` times the distance from the beam's dot in the previous frame.
   Blobs left over are counted as ``extra``. Only each beam's search window is looked at (its
   curve's bounding box grown by ``search_margin_px``): a red spot farther away is not seen at all.
   With the previous frame's three dots, first only squares around them (``track_px``), the
   search windows when that does not find all three;
5. the beam length of each dot: closest approach between the beam and the camera ray through the
   dot (:func:`triangulate`).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from companion.calibration import CameraCalibration
from companion.laser_beams import BEAMS, BeamRig

GREY_REASON = "grey image: the laser dots need a colour (BGR) camera"
SATURATED_REASON = "image saturated"
SAME_BLOB_PX = 0.5  # two windows' blobs closer than this are one, pixels
ROUND_TRIP_TOLERANCE = 1e-6  # a curve sample counts if the lens model maps it back to its ray, normalised units


@dataclass(frozen=True)
class DotParams:
    """Thresholds of the dot detector."""

    min_dominance: int = 40  # R - max(G, B) above this is laser red, grey levels
    min_red_px: int = 2  # a blob needs this many pixels redder than min_fringe_dominance ...
    min_fringe_dominance: int = 10  # ... R - max(G, B), grey levels: a dot washed out to white keeps a pink fringe
    min_area_px: int = 3  # smaller blobs are noise, pixels
    max_area_px: int = 2000  # larger ones are red objects, not dots, pixels
    max_curve_distance_px: float = 4.0  # a beam's dot lies within this of the beam's image curve, pixels
    prior_weight: float = 0.05  # cost per pixel from the previous frame's dot, in pixels of curve distance
    max_candidates: int = 8  # the strongest blobs near a curve that the assignment considers
    saturation_level: int = 250  # a pixel with all channels at or above this is saturated, grey levels
    max_saturated_fraction: float = 0.25  # a larger share of saturated pixels: no dots
    curve_samples: int = 256  # samples of each beam's image curve, evenly spaced in 1 / length
    # Dots are looked for only in each beam's search window: its image curve's bounding box grown by
    # this (pixels; a blob farther from the curve is refused anyway, and one this wide is no dot):
    # about a sixth of a 640x480 image instead of all of it.
    search_margin_px: int = 30
    saturation_stride_px: int = 8  # the saturated share is estimated on every n-th pixel of every n-th row (4800 of 640x480)
    # With the previous frame's three dots known, each is looked for first within this (pixels, half
    # the side of a square) of where it was; the whole search windows only if that misses one.
    track_px: int = 30


@dataclass(frozen=True)
class Dots:
    """The dots of one image, row i = beam i."""

    pixels: np.ndarray  # (3, 2) float64 (u, v) pixels; NaN where not found
    found: np.ndarray  # (3,) bool
    lengths_m: np.ndarray  # (3,) beam length from its origin to the dot (triangulated), m; NaN where not found
    miss_m: np.ndarray  # (3,) closest distance between the beam and the camera ray through the dot, m; NaN
    extra: int  # red blobs in the search windows not taken by any beam
    reason: str | None = None  # why the image gave no dots at all (grey, saturated, wrong size); None otherwise


@dataclass(frozen=True)
class Blobs:
    """Red blobs of one image: (N, 2) centroid pixels and (N,) summed dominance (grey levels * px)."""

    centroids: np.ndarray
    strengths: np.ndarray


def triangulate(origin: np.ndarray, direction: np.ndarray, camera_centre: np.ndarray,
                ray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest approach of the beam ``origin + l * direction`` and the camera ray ``camera_centre +
    s * ray`` (each (..., 3), broadcast, in one frame, body FRD for the detector, metres;
    ``direction`` and ``ray`` need not be unit): (beam length l in units of |direction|, m for a
    unit direction, (...); miss distance between the two lines, m, (...); the point on the beam at
    l, (..., 3) m). The beam is taken as exact (calibrated), so the dot is placed on it. Parallel
    lines give NaN."""
    d, r = np.asarray(direction, dtype=float), np.asarray(ray, dtype=float)
    w = np.asarray(origin, dtype=float) - np.asarray(camera_centre, dtype=float)
    a, b, c = (np.sum(d * d, axis=-1), np.sum(d * r, axis=-1), np.sum(r * r, axis=-1))
    rw, dw = np.sum(r * w, axis=-1), np.sum(d * w, axis=-1)
    denominator = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        parallel = ~(denominator > 1e-12 * a * c)
        denominator = np.where(parallel, np.nan, denominator)
        length = (b * rw - c * dw) / denominator
        along_ray = (a * rw - b * dw) / denominator
    point = origin + length[..., None] * d
    miss = np.linalg.norm(point - (camera_centre + along_ray[..., None] * r), axis=-1)
    return length, miss, point


def red_dominance(image_bgr: np.ndarray) -> np.ndarray:
    """(H, W) uint8 ``max(R - max(G, B), 0)`` of an (H, W, 3) BGR uint8 image, grey levels."""
    blue, green, red = cv2.split(image_bgr)
    return cv2.subtract(red, cv2.max(green, blue))


def darkest_channel(image_bgr: np.ndarray) -> np.ndarray:
    """(H, W) uint8 min(B, G, R) of a BGR image."""
    return cv2.min(cv2.min(image_bgr[..., 0], image_bgr[..., 1]), image_bgr[..., 2])


def saturated_fraction(image_bgr: np.ndarray, level: int, stride: int = 1) -> float:
    """Share (0..1) of the pixels of a BGR image with all three channels at or above ``level``,
    over every ``stride``-th pixel of every ``stride``-th row."""
    darkest = darkest_channel(np.ascontiguousarray(image_bgr[::stride, ::stride]))
    return cv2.countNonZero(cv2.compare(darkest, level, cv2.CMP_GE)) / darkest.size


def laser_weight(image_bgr: np.ndarray, saturation_level: int, min_dominance: int) -> tuple[np.ndarray, np.ndarray]:
    """((H, W) uint8 weight, (H, W) uint8 red dominance) of an (H, W, 3) BGR image: the weight is
    the red dominance R - max(G, B), except 255 where the red channel is saturated (at or above
    ``saturation_level``) while the dominance is at most ``min_dominance``. A laser dot on a bright
    surface (white paper) saturates green too at its core, where the dominance drops to about 0
    and leaves a ring: the weight fills that hole. (White paper itself stays below saturation in
    red; a lamp that does not is no dot: see find_blobs.)"""
    dominance = red_dominance(image_bgr)
    red_saturated = cv2.compare(image_bgr[..., 2], saturation_level, cv2.CMP_GE)
    washed_out = cv2.bitwise_and(red_saturated, cv2.compare(dominance, min_dominance, cv2.CMP_LE))
    return cv2.max(dominance, washed_out), dominance


def find_blobs(weight: np.ndarray, dominance: np.ndarray, params: DotParams,
               offset: tuple[int, int] = (0, 0)) -> Blobs:
    """The blobs of pixels with ``weight`` above ``params.min_dominance`` (8-connected) whose area is
    within the params' limits and that hold at least ``min_red_px`` reddish pixels (``dominance``
    above ``min_fringe_dominance``: a neutral saturated lamp or reflection is no dot), with their
    weight-weighted centroids (pixels, plus ``offset`` (u, v): where the arrays sit in the image)."""
    mask = cv2.compare(weight, params.min_dominance, cv2.CMP_GT)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero((areas >= params.min_area_px) & (areas <= params.max_area_px)) + 1
    found = [weighted_centroid(weight, labels, stats[k], k) for k in keep
             if red_pixels(dominance, labels, stats[k], k, params.min_fringe_dominance) >= params.min_red_px]
    return Blobs(np.array([c for c, _ in found], dtype=float).reshape(-1, 2) + np.array(offset, dtype=float),
                 np.array([s for _, s in found], dtype=float))


def _box(stat: np.ndarray) -> tuple[slice, slice]:
    """The (rows, columns) slices of a connected component's bounding box."""
    x, y = stat[cv2.CC_STAT_LEFT], stat[cv2.CC_STAT_TOP]
    return slice(y, y + stat[cv2.CC_STAT_HEIGHT]), slice(x, x + stat[cv2.CC_STAT_WIDTH])


def red_pixels(dominance: np.ndarray, labels: np.ndarray, stat: np.ndarray, label: int, threshold: int) -> int:
    """How many pixels of component ``label`` have ``dominance`` above ``threshold``."""
    rows, cols = _box(stat)
    return int(np.count_nonzero((labels[rows, cols] == label) & (dominance[rows, cols] > threshold)))


def weighted_centroid(weight: np.ndarray, labels: np.ndarray, stat: np.ndarray,
                      label: int) -> tuple[np.ndarray, float]:
    """((2,) pixel centroid of component ``label`` weighted by ``weight``, summed weight)."""
    rows, cols = _box(stat)
    weights = np.where(labels[rows, cols] == label, weight[rows, cols], 0).astype(float)
    total = weights.sum()
    u = cols.start + (weights.sum(axis=0) @ np.arange(weights.shape[1])) / total
    v = rows.start + (weights.sum(axis=1) @ np.arange(weights.shape[0])) / total
    return np.array([u, v]), float(total)


def curve_segments(calibration: CameraCalibration, optical_to_body: np.ndarray, camera_origin_body: np.ndarray,
                   origin: np.ndarray, direction: np.ndarray, length_range_m: tuple[float, float],
                   samples: int) -> np.ndarray:
    """(S, 2, 2) pixel segments [start, end] of the image curve of the beam ``origin + l *
    direction`` (body FRD, m) for l in ``length_range_m`` (m): samples evenly spaced in 1 / l,
    through the lens; samples behind the camera or beyond a fold of the distortion model are
    left out, with the segments that touch them."""
    lengths = 1.0 / np.linspace(1.0 / length_range_m[0], 1.0 / length_range_m[1], samples)
    optical = (origin + lengths[:, None] * direction - camera_origin_body) @ optical_to_body
    pixels = calibration.project(optical)
    valid = np.all(np.isfinite(pixels), axis=1)
    back = np.full_like(pixels, np.nan)
    back[valid] = calibration.undistort_points(pixels[valid])
    with np.errstate(divide="ignore", invalid="ignore"):
        expected = optical[:, :2] / optical[:, 2:]
    valid &= np.all(np.abs(back - expected) < ROUND_TRIP_TOLERANCE, axis=1)
    both = valid[:-1] & valid[1:]
    return np.stack((pixels[:-1][both], pixels[1:][both]), axis=1)


def distance_to_segments(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """(N,) distance (pixels) from each of the (N, 2) points to the nearest of the (S, 2, 2)
    segments; inf without segments."""
    if len(segments) == 0:
        return np.full(len(points), np.inf)
    start, step = segments[:, 0], segments[:, 1] - segments[:, 0]
    offset = points[:, None, :] - start[None]
    t = np.clip(np.sum(offset * step, axis=2) / np.maximum(np.sum(step * step, axis=1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(offset - t[..., None] * step, axis=2).min(axis=1)


def search_window(segments: np.ndarray, margin_px: int, width: int, height: int) -> tuple[slice, slice] | None:
    """(rows, columns) of the image (``width`` x ``height`` px) within ``margin_px`` of the bounding
    box of a curve's (K, 2, 2) segments (pixels), None for a curve outside the image."""
    if len(segments) == 0:
        return None
    points = segments.reshape(-1, 2)
    low = np.floor(points.min(axis=0)).astype(int) - margin_px
    high = np.ceil(points.max(axis=0)).astype(int) + margin_px + 1
    cols = slice(max(int(low[0]), 0), min(int(high[0]), width))
    rows = slice(max(int(low[1]), 0), min(int(high[1]), height))
    return (rows, cols) if rows.start < rows.stop and cols.start < cols.stop else None


@functools.lru_cache(maxsize=None)
def _assignments(beams: int, n: int) -> np.ndarray:
    """(M, beams) every assignment of ``n`` blobs to ``beams`` beams (-1 = none), no blob twice,
    in ``itertools.product`` order."""
    rows = [c for c in itertools.product(range(-1, n), repeat=beams)
            if len({k for k in c if k >= 0}) == sum(k >= 0 for k in c)]
    return np.array(rows, dtype=int).reshape(-1, beams)


def best_assignment(cost: np.ndarray) -> tuple[int, ...]:
    """For a (beams, N) cost matrix (inf = not admissible), the blob index per beam (-1 = none),
    no blob twice: most beams assigned first, then the least summed cost (the first such in
    ``itertools.product`` order on a tie). Exhaustive, over a cached table of the assignments."""
    beams, n = cost.shape
    choices = _assignments(beams, n)
    assigned = choices >= 0
    costs = np.concatenate((cost, np.zeros((beams, 1))), axis=1)[np.arange(beams), np.where(assigned, choices, n)]
    admissible = np.flatnonzero(np.all(np.isfinite(costs), axis=1))
    order = np.lexsort((costs[admissible].sum(axis=1), -assigned[admissible].sum(axis=1)))
    return tuple(int(k) for k in choices[admissible[order[0]]])


def no_dots(reason: str | None, extra: int = 0) -> Dots:
    """The result without any dot."""
    nan = np.full(BEAMS, np.nan)
    return Dots(np.full((BEAMS, 2), np.nan), np.zeros(BEAMS, dtype=bool), nan, nan.copy(), extra, reason)


class DotDetector:
    """The laser dots of the beams of ``rig`` seen by a camera of ``calibration`` fixed to the body:
    ``optical_to_body`` (3x3 rotation, optical -> body FRD) and ``camera_origin_body`` (its centre,
    body FRD, m). ``length_range_m``: the beam lengths (m) at which dots are looked for."""

    def __init__(self, calibration: CameraCalibration, optical_to_body: np.ndarray, camera_origin_body: np.ndarray,
                 rig: BeamRig, params: DotParams = DotParams(),
                 length_range_m: tuple[float, float] = (0.2, 6.0)) -> None:
        if not 0.0 < length_range_m[0] < length_range_m[1]:
            raise ValueError(f"length_range_m must be (min, max) with 0 < min < max, got {length_range_m}")
        self.calibration = calibration
        self.optical_to_body = np.asarray(optical_to_body, dtype=float).reshape(3, 3)
        self.camera_origin_body = np.asarray(camera_origin_body, dtype=float).reshape(3)
        self.rig = rig
        self.params = params
        self.curves = [curve_segments(calibration, self.optical_to_body, self.camera_origin_body, o, d,
                                      length_range_m, params.curve_samples)
                       for o, d in zip(rig.origins, rig.directions)]
        self.windows = [w for w in (search_window(c, params.search_margin_px, calibration.width, calibration.height)
                                    for c in self.curves) if w is not None]

    def blobs(self, image_bgr: np.ndarray, windows: list[tuple[slice, slice]]) -> Blobs:
        """The red blobs of the ``windows`` ((rows, columns) of the image; one blob seen by two
        overlapping windows counts once)."""
        p = self.params
        found = [find_blobs(*laser_weight(image_bgr[rows, cols], p.saturation_level, p.min_dominance), p,
                            (cols.start, rows.start)) for rows, cols in windows]
        centroids = np.concatenate([b.centroids for b in found]).reshape(-1, 2)
        strengths = np.concatenate([b.strengths for b in found])
        keep = [i for i in range(len(centroids))
                if not np.any(np.linalg.norm(centroids[:i] - centroids[i], axis=1) < SAME_BLOB_PX)]
        return Blobs(centroids[keep], strengths[keep])

    def tracking_windows(self, previous: np.ndarray) -> list[tuple[slice, slice]]:
        """Squares of half-side ``track_px`` around the (3, 2) dot pixels of the previous frame."""
        t, width, height = self.params.track_px, self.calibration.width, self.calibration.height
        return [(slice(max(int(v) - t, 0), min(int(v) + t + 1, height)),
                 slice(max(int(u) - t, 0), min(int(u) + t + 1, width))) for u, v in previous]

    def detect(self, image_bgr: np.ndarray, previous: np.ndarray | None = None) -> Dots:
        """The dots in ``image_bgr`` ((H, W, 3) uint8 BGR at the calibration's size); ``previous``:
        the (3, 2) dot pixels of the previous frame (NaN rows = unknown), a prior for the identity
        and, when all three are known, where to look first (``track_px``)."""
        reason = self.unusable(image_bgr)
        if reason is not None:
            return no_dots(reason)
        if previous is not None and np.all(np.isfinite(previous)):
            dots = self.match(self.blobs(image_bgr, self.tracking_windows(previous)), previous)
            if dots.found.all():
                return dots
        return self.match(self.blobs(image_bgr, self.windows), previous)

    def match(self, blobs: Blobs, previous: np.ndarray | None) -> Dots:
        """The dots among ``blobs``: each beam's blob (module docstring, step 4) and its length."""
        if len(blobs.strengths) == 0:
            return no_dots(None)
        distances = self.curve_distances(blobs.centroids)
        candidates = self.candidates(distances, blobs.strengths)
        choice = best_assignment(self.costs(distances[:, candidates], blobs.centroids[candidates], previous))
        pixels = np.full((BEAMS, 2), np.nan)
        for beam, k in enumerate(choice):
            if k >= 0:
                pixels[beam] = blobs.centroids[candidates[k]]
        found = np.all(np.isfinite(pixels), axis=1)
        lengths, miss = self.lengths(pixels)
        return Dots(pixels, found, lengths, miss, len(blobs.strengths) - int(found.sum()))

    def unusable(self, image: np.ndarray) -> str | None:
        """Why ``image`` cannot give dots, or None."""
        if image.ndim == 2:
            return GREY_REASON
        height, width = image.shape[:2]
        if (width, height) != (self.calibration.width, self.calibration.height):
            return (f"image {width}x{height}, camera calibrated at "
                    f"{self.calibration.width}x{self.calibration.height}")
        p = self.params
        if saturated_fraction(image, p.saturation_level, p.saturation_stride_px) > p.max_saturated_fraction:
            return SATURATED_REASON
        return None

    def curve_distances(self, pixels: np.ndarray) -> np.ndarray:
        """(3, N) distance (pixels) of each of the (N, 2) pixels from each beam's image curve."""
        return np.array([distance_to_segments(pixels, segments) for segments in self.curves])

    def candidates(self, distances: np.ndarray, strengths: np.ndarray) -> np.ndarray:
        """Indices of the blobs within reach of some beam's curve (``distances``: (3, N) pixels from
        each curve), at most ``max_candidates``, the strongest (``strengths``, (N,))."""
        near = np.flatnonzero(distances.min(axis=0) <= self.params.max_curve_distance_px)
        return near[np.argsort(-strengths[near], kind="stable")][:self.params.max_candidates]

    def costs(self, distances: np.ndarray, pixels: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
        """(3, N) assignment cost (pixels) of each beam for each of the (N, 2) candidate ``pixels``:
        the distance from the beam's curve (``distances``, (3, N); inf beyond
        ``max_curve_distance_px``) plus ``prior_weight`` times the distance from the beam's dot in
        ``previous`` ((3, 2), NaN rows = unknown: 0)."""
        cost = np.where(distances <= self.params.max_curve_distance_px, distances, np.inf)
        if previous is not None:
            moved = np.linalg.norm(pixels[None, :, :] - np.asarray(previous, dtype=float)[:, None, :], axis=2)
            cost += self.params.prior_weight * np.nan_to_num(moved, nan=0.0)
        return cost

    def lengths(self, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((..., 3) beam lengths m, (..., 3) miss distances m) of (..., 3, 2) dot pixels, row i
        the dot of beam i (NaN rows give NaN)."""
        pixels = np.asarray(pixels, dtype=float)
        flat = pixels.reshape(-1, 2)
        rays = np.column_stack((self.calibration.undistort_points(flat), np.ones(len(flat)))) @ self.optical_to_body.T
        rays = rays.reshape(pixels.shape[:-1] + (3,))
        lengths, miss, _ = triangulate(self.rig.origins, self.rig.directions, self.camera_origin_body, rays)
        return lengths, miss

    def length_sigma_m(self, pixels: np.ndarray, sigma_px: float) -> np.ndarray:
        """(3,) 1-sigma (m) of the triangulated beam lengths of the (3, 2) dot ``pixels`` for a
        centroid error of ``sigma_px`` (px, 1-sigma per axis): the length's gradient over the image
        (central differences, 0.5 px) times ``sigma_px``. NaN for a missing dot."""
        step = 0.5
        offsets = np.array([[step, 0.0], [-step, 0.0], [0.0, step], [0.0, -step]])
        lengths, _ = self.lengths(np.asarray(pixels, dtype=float)[None] + offsets[:, None, :])
        gradients = (lengths[0::2] - lengths[1::2]) / (2.0 * step)
        return np.hypot(*gradients) * sigma_px
