"""Poses of a walk's scans by matching each scan to the ones before it (a log without poses).

For ``companion map build`` on a log that carries no poses (a scanner carried through a building,
a BreezySLAM or npz recording): the scans' poses are estimated here, then the map is built from
them (companion/nav/map_build.py) as from a log's own poses. Plain numpy and OpenCV, no I/O.

Frames: scans are sensor-frame points (FRD: x forward, y right, metres); poses are x north, y east
(metres) and yaw from north towards east (radians) in the map frame, whose origin and north are
the first scan's pose (0, 0, 0).

Method (a scan-to-map matcher in the manner of Hector SLAM / Olson's correlative matching, no loop
closure):

1. the local map is an occupancy image (``resolution_m`` cells) of the keyframe scans' points
   within ``window_m`` of the newest keyframe, and from its distance transform a score per cell,
   ``exp(-d^2 / (2 sigma^2))`` for the distance d to the nearest occupied cell;
2. each scan is predicted with the previous step's motion (constant velocity), then placed by a
   coarse search over x, y and yaw around the prediction (the sum of its points' scores, at the
   nearest cell), and refined by a finer search around the best (scores interpolated);
3. a scan becomes a keyframe (its points join the map) once it moved ``keyframe_m`` or turned
   ``keyframe_deg`` from the last keyframe.

Without loop closure the poses drift along a long walk (a few per cent of the distance in
corridors, whose along-track direction only the ends and doors measure): good for a room or a
floor walked once, not for a campus.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np

from companion.frames import planar_increment, planar_moved, planar_rotation, wrap_pi

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class ScanPoseParams:
    """Thresholds of the scan-to-map matcher."""

    resolution_m: float = 0.03  # map cell
    window_m: float = 30.0  # side of the local map around the newest keyframe
    max_range_m: float = 15.0  # returns further away are not used
    max_points: int = 200  # points of a scan used for matching (evenly subsampled)
    sigma_m: float = 0.05  # a point this far from the map scores exp(-1/2)
    coarse_xy_m: float = 0.3  # coarse search: +/- this around the prediction ...
    coarse_xy_step_m: float = 0.05  # ... in these steps
    coarse_yaw_deg: float = 6.0  # +/- this ...
    coarse_yaw_step_deg: float = 1.0  # ... in these steps
    fine_steps: int = 5  # fine search: +/- one coarse step in this many sub-steps each side
    keyframe_m: float = 0.15  # a scan this far from the last keyframe joins the map ...
    keyframe_deg: float = 5.0  # ... or turned this much
    keyframes: int = 120  # the map keeps the newest this many keyframes


def scan_poses(scans: Iterable[tuple[np.ndarray, np.ndarray]], params: ScanPoseParams = ScanPoseParams()) -> np.ndarray:
    """(S, 3) poses [x m, y m, yaw rad] of ``scans`` ((points (N, 2) sensor frame m, valid (N,))),
    the first at (0, 0, 0); ValueError if a scan has too few returns to place."""
    tracker = _Tracker(params)
    return np.array([tracker.place(points, valid) for points, valid in scans]).reshape(-1, 3)


class _Tracker:
    """The matcher's state: the keyframes' points and the local map built from them."""

    def __init__(self, params: ScanPoseParams) -> None:
        self.p = params
        self.keyframe_points: list[np.ndarray] = []  # (K, 2) map-frame points per keyframe
        self.last_keyframe: Pose | None = None
        self.poses: list[Pose] = []
        self.score = np.zeros((0, 0), dtype=np.float32)  # per cell: exp(-d^2 / 2 sigma^2), d to the nearest map point
        self.field_origin = np.zeros(2)  # map-frame position of cell (0, 0)'s corner

    def place(self, points: np.ndarray, valid: np.ndarray) -> Pose:
        """The pose of one scan (and the map updated with it when it is a keyframe)."""
        local = self._usable(points, valid)
        if not self.poses:
            pose: Pose = (0.0, 0.0, 0.0)
        else:
            pose = self._match(local, self._predicted())
        self.poses.append(pose)
        if self.last_keyframe is None or self._moved(pose, self.last_keyframe):
            self._add_keyframe(local, pose)
        return pose

    def _usable(self, points: np.ndarray, valid: np.ndarray) -> np.ndarray:
        r = np.hypot(points[:, 0], points[:, 1])
        keep = valid & np.isfinite(r) & (r > 0.0) & (r <= self.p.max_range_m)
        local = points[keep]
        if local.shape[0] < 20:
            raise ValueError(f"scan {len(self.poses)}: {local.shape[0]} returns within "
                             f"{self.p.max_range_m:g} m, too few to place it")
        step = max(1, local.shape[0] // self.p.max_points)
        return local[::step]

    def _predicted(self) -> Pose:
        """The newest pose moved again by the newest step (constant velocity in its body frame)."""
        if len(self.poses) < 2:
            return self.poses[-1]
        return planar_moved(self.poses[-1], *planar_increment(self.poses[-2], self.poses[-1]))

    def _match(self, local: np.ndarray, guess: Pose) -> Pose:
        p = self.p
        coarse = self._search(local, guess, p.coarse_xy_m, p.coarse_xy_step_m,
                              math.radians(p.coarse_yaw_deg), math.radians(p.coarse_yaw_step_deg), False)
        fine_xy, fine_yaw = p.coarse_xy_step_m / p.fine_steps, math.radians(p.coarse_yaw_step_deg) / p.fine_steps
        return self._search(local, coarse, p.coarse_xy_step_m, fine_xy, math.radians(p.coarse_yaw_step_deg),
                            fine_yaw, True)

    def _search(self, local: np.ndarray, centre: Pose, xy_half: float, xy_step: float, yaw_half: float,
                yaw_step: float, bilinear: bool) -> Pose:
        """The best-scoring pose on the grid around ``centre``; the score interpolated between cells
        (``bilinear``) or taken at the nearest one (the coarse search)."""
        res = self.p.resolution_m
        offsets = np.arange(-xy_half, xy_half + 1e-9, xy_step)
        shifts = np.stack(np.meshgrid(offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 2)  # (T, 2) m
        best, best_pose = -1.0, centre
        for dyaw in np.arange(-yaw_half, yaw_half + 1e-12, yaw_step):
            yaw = centre[2] + dyaw
            world = local @ planar_rotation(yaw).T + np.array(centre[:2])  # (N, 2)
            cells = (world[None, :, :] + shifts[:, None, :] - self.field_origin) / res - 0.5  # (T, N, 2), cell centres
            scores = (self._bilinear(cells) if bilinear else self._nearest(cells)).sum(axis=1)
            k = int(np.argmax(scores))
            if scores[k] > best:
                best, best_pose = float(scores[k]), (centre[0] + shifts[k, 0], centre[1] + shifts[k, 1], wrap_pi(yaw))
        return best_pose

    def _nearest(self, cells: np.ndarray) -> np.ndarray:
        """The score image at the cells nearest to fractional ``cells`` (..., 2); its border cells
        (always 0) stand for everything outside."""
        h, w = self.score.shape
        i = np.clip(np.rint(cells[..., 0]).astype(np.intp), 0, h - 1)
        j = np.clip(np.rint(cells[..., 1]).astype(np.intp), 0, w - 1)
        return self.score.ravel()[i * w + j]

    def _bilinear(self, cells: np.ndarray) -> np.ndarray:
        """The score image interpolated at fractional ``cells`` (..., 2), 0 outside (see _nearest)."""
        h, w = self.score.shape
        ci = np.clip(cells[..., 0], 0, h - 2)
        cj = np.clip(cells[..., 1], 0, w - 2)
        i0, j0 = ci.astype(np.intp), cj.astype(np.intp)
        fi, fj = ci - i0, cj - j0
        f = self.score.ravel()
        k = i0 * w + j0
        return ((1 - fi) * ((1 - fj) * f[k] + fj * f[k + 1]) + fi * ((1 - fj) * f[k + w] + fj * f[k + w + 1]))

    def _moved(self, pose: Pose, keyframe: Pose) -> bool:
        return (math.dist(pose[:2], keyframe[:2]) >= self.p.keyframe_m
                or abs(wrap_pi(pose[2] - keyframe[2])) >= math.radians(self.p.keyframe_deg))

    def _add_keyframe(self, local: np.ndarray, pose: Pose) -> None:
        """Add the scan's points to the map and rebuild the distance field around ``pose``."""
        self.keyframe_points.append(local @ planar_rotation(pose[2]).T + np.array(pose[:2]))
        self.keyframe_points = self.keyframe_points[-self.p.keyframes:]
        self.last_keyframe = pose
        res, half = self.p.resolution_m, self.p.window_m / 2
        self.field_origin = np.array(pose[:2]) - half
        size = int(round(self.p.window_m / res))
        free = np.full((size, size), 255, dtype=np.uint8)  # 0 = occupied, for cv2.distanceTransform
        cells = np.floor((np.vstack(self.keyframe_points) - self.field_origin) / res).astype(int)
        inside = (cells >= 0).all(axis=1) & (cells < size).all(axis=1)
        free[cells[inside, 0], cells[inside, 1]] = 0
        distance = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(res)
        score = np.exp(-0.5 * (distance / np.float32(self.p.sigma_m)) ** 2)
        score[[0, -1], :] = 0.0  # the border stands for everything outside the window
        score[:, [0, -1]] = 0.0
        self.score = score
