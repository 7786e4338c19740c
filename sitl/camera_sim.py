"""Simulated camera: images rendered from simulator ground truth (``kind: camera, backend: sim``).

Intrinsics: a :class:`~companion.calibration.CameraCalibration`, from the settings (pinhole ``fx``,
``fy`` or ``hfov_deg``, ``cx``, ``cy``, OpenCV plumb_bob ``distortion``) or from a calibration file
(plumb_bob or equidistant). Each pixel's ray is found once (sitl/camera_lens.py), so that a point
projected with cv2.projectPoints lands where the renderer draws it; pixels the lens model cannot
reach (beyond a fold of the distortion polynomial) stay black.

Frames: the optical frame (OpenCV: x right, y down in the image, z along the optical axis) is
fixed in the camera's sensor frame, which its mount (``sensors.<name>.mount``, drivers/mount.py)
places in body FRD. The sensor frame is FRD-like, as for a scanner: x along the optical axis,
y towards the image's right, z towards the image's bottom. Mount rpy [0, 0, 0] looks forward
with the image upright; [0, -90, 0] looks down with the image's top towards the body's front.

Scene: the floor, floor markers (ArUco), walls and obstacles of the world (sitl/camera_scene.py);
in a world with ``ground: terrain``, textured ground to the horizon under a smooth sky (a fixed
wing's forward camera: config/cameras/forward-90-640.yaml).
Without ``laser_beams`` the image is grey, (H, W) uint8. With them, it is BGR (H, W, 3) uint8: the
grey scene in all three channels plus the dots of the vehicle's laser beams (the true rig, body
FRD), mostly in red, wherever they meet the world and the camera sees them (sitl/laser_spots.py:
their size, brightness, speckle and blur; a dot hidden by an obstacle or a wall is not drawn);
``laser_hits`` gives the points the renderer used.

Timing: capture times ``t`` (mid-exposure, the Frame's ``t_capture``, daemon clock s) lie on a
grid ``t0 + k / fps`` from :meth:`SimulatedCamera.open`; the frame arrives at ``t + exposure_s / 2
+ latency_s`` (the end of the exposure plus readout and transfer) plus the rendering time,
waited for on the daemon clock like the simulated scanner (sitl/lidar_sim.py). ``sequence`` is the
grid index k: a reader more than a period late skips to the latest due frame, and a frame without
truth yields nothing. Rendering runs on a worker thread (inline in lockstep: companion.clock.compute).

Motion blur (``motion_blur: true``): the image is the mean of K renders at poses spread evenly over
the exposure, positions linear and attitude along the shortest rotation between the truth at its
start and at its end; K is the largest image motion in pixels (from the rotation, and from the
translation over the nearest surface), 1 to :data:`MAX_BLUR_SAMPLES`. Noise: Gaussian, independent
per pixel (and channel), ``noise_sigma`` grey levels, added after the blur, from a generator seeded with
(``seed``, k); the image is then rounded and clipped to 0..255. Before the noise, the image
(scene and dots) is multiplied by ``gain``: from 1.09 the markers' white paper (235) saturates,
from 2 half the floor (mean 128).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from companion import clock
from companion.calibration import CameraCalibration
from companion.frames import rotation_from_quat
from companion.laser_beams import BeamRigConfig
from companion.messages import Frame
from companion.schema import meta
from companion.world import World
from drivers.base import Backend
from drivers.mount import OPTICAL_TO_SENSOR, Mount
from sitl.camera_lens import PixelRays
from sitl.camera_scene import Scene
from sitl.capture_grid import CaptureGrid
from sitl.laser_spots import LaserSpots
from sitl.truth import TruthLike, TruthPose

MAX_BLUR_SAMPLES = 16
NEAREST_SURFACE_MIN_M = 0.05  # for the blur's sample count
NEAR_M = 1e-3  # what is nearer to the camera's image plane is not drawn, m

_INTRINSICS = ("width", "height", "hfov_deg", "fx", "fy", "cx", "cy", "distortion")


@dataclass(frozen=True)
class SimCameraSettings:
    """``settings:`` of a camera with ``backend: sim`` (a companion.schema dataclass)."""

    width: int | None = field(default=None, metadata=meta("Image width, pixels; null = 640.", (16, 4096)))
    height: int | None = field(default=None, metadata=meta("Image height, pixels; null = 480.", (16, 4096)))
    hfov_deg: float | None = field(default=None, metadata=meta(
        "Horizontal field of view of the pinhole, degrees (instead of fx); null with fx null = 90.", (5, 170)))
    fx: float | None = field(default=None, metadata=meta("Focal length along x, pixels.", (1, 100000)))
    fy: float | None = field(default=None, metadata=meta("Focal length along y, pixels; null = fx.", (1, 100000)))
    cx: float | None = field(default=None, metadata=meta(
        "Principal point column, pixels (integers at pixel centres); null = the image centre.", (0, 4096)))
    cy: float | None = field(default=None, metadata=meta("Principal point row, pixels; null = the image centre.",
                                                         (0, 4096)))
    distortion: tuple[float, ...] | None = field(default=None, metadata=meta(
        "OpenCV plumb_bob coefficients k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]]; null = none.", (-100, 100)))
    calibration: str | None = field(default=None, metadata=meta(
        "Calibration file (OpenCV or ROS YAML, relative to the config) giving all the intrinsics instead of the "
        "keys above."))
    fps: float = field(default=30.0, metadata=meta("Frame rate, Hz.", (0.5, 200)))
    exposure_s: float = field(default=0.005, metadata=meta("Exposure time, seconds.", (1e-5, 0.5)))
    latency_s: float = field(default=0.02, metadata=meta(
        "From the end of the exposure to the frame's delivery (readout, transfer), seconds.", (0, 1)))
    noise_sigma: float = field(default=2.0, metadata=meta("Pixel noise, 1-sigma grey levels.", (0, 100)))
    motion_blur: bool = field(default=False, metadata=meta(
        "Blur along the image motion during the exposure (costs up to 16 renders per frame)."))
    seed: int = field(default=0, metadata=meta("Seed of the pixel noise.", (0, 999999)))
    floor_seed: int = field(default=0, metadata=meta(
        "Seed of the floor texture: give every camera of one simulation the same, so they see one floor.",
        (0, 999999)))
    gain: float = field(default=1.0, metadata=meta(
        "Multiplies the image (scene and laser dots) before the noise: from 1.09 the markers' white paper (235) "
        "saturates, from 2 half the floor.", (0.01, 100)))
    laser_beams: BeamRigConfig | None = field(default=None, metadata=meta(
        "The TRUE laser beam rig on the vehicle, body FRD (keys angle_deg, azimuth_deg, origin_m, origins_m, "
        "directions, as the laser-dot pipeline's beam rig); its dots are drawn and the image becomes BGR. Give it "
        "other values than the pipeline's rig to simulate a mounting error. null = no lasers, grey images."))
    laser_spot_m: float = field(default=0.01, metadata=meta(
        "1/e^2 diameter of a laser beam where it meets a surface, metres (stretched on a surface hit obliquely).",
        (1e-4, 1)))
    laser_peak: float = field(default=400.0, metadata=meta(
        "Red level added at the centre of a laser dot, grey levels before saturation (the default saturates the "
        "dot's core).", (0, 10000)))
    laser_speckle_px: float = field(default=0.5, metadata=meta(
        "Laser speckle: 1-sigma random displacement of each dot's apparent centre per frame and axis, pixels "
        "(seeded with seed and the frame number).", (0, 50)))
    laser_bloom_px: float = field(default=1.0, metadata=meta(
        "Optical blur of the laser dots (lens point spread), 1-sigma, pixels.", (0, 20)))

    def validate(self) -> tuple[str, str] | None:
        given = [k for k in _INTRINSICS if getattr(self, k) is not None]
        if self.calibration is not None and given:
            return given[0], "the calibration file gives the intrinsics: leave this out, or leave out calibration"
        if self.fx is not None and self.hfov_deg is not None:
            return "hfov_deg", "give fx or hfov_deg, not both"
        if self.fy is not None and self.fx is None:
            return "fy", "needs fx"
        for key, size in (("cx", self.width or 640), ("cy", self.height or 480)):
            if (getattr(self, key) or 0.0) > size:
                return key, f"the principal point must lie in the image, {size} pixels across"
        if self.distortion is not None and len(self.distortion) not in (4, 5, 8, 12):
            return "distortion", f"give 4, 5, 8 or 12 coefficients (no tilted sensor), got {len(self.distortion)}"
        if self.exposure_s >= 1.0 / self.fps:
            return "exposure_s", f"must be shorter than the frame period 1/fps = {1.0 / self.fps:g} s"
        return None

    def intrinsics(self) -> CameraCalibration:
        """The plumb_bob calibration the intrinsics keys describe (those not given take their defaults)."""
        width, height = self.width or 640, self.height or 480
        fx = self.fx if self.fx is not None else (width / 2) / math.tan(math.radians(self.hfov_deg or 90.0) / 2)
        fy = self.fy if self.fy is not None else fx
        cx = self.cx if self.cx is not None else (width - 1) / 2
        cy = self.cy if self.cy is not None else (height - 1) / 2
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return CameraCalibration(width, height, K, np.array(self.distortion or (), dtype=float))


class SimulatedCamera(Backend[Frame]):
    """A camera of ``calibration`` on ``mount``, seeing ``world`` from ``truth``'s poses."""

    def __init__(self, camera_id: str, settings: SimCameraSettings, calibration: CameraCalibration, mount: Mount,
                 world: World, truth: TruthLike) -> None:
        self.camera_id = camera_id
        self.settings = settings
        self.calibration = calibration
        self.mount = mount
        self.truth = truth
        self.scene = Scene(world, settings.floor_seed)
        self.rays = PixelRays.make(calibration)
        self.lasers = None if settings.laser_beams is None else LaserSpots(
            settings.laser_beams.rig(), self.scene, calibration, self.rays.reached, mount, settings.laser_spot_m,
            settings.laser_peak, settings.laser_speckle_px, settings.laser_bloom_px, settings.seed)
        self.grid = CaptureGrid(1.0 / settings.fps)
        self.description = f"simulated camera {calibration.width}x{calibration.height}"

    async def open(self) -> None:
        """Start the frame grid at the current daemon time."""
        self.grid.start()

    async def read(self) -> Frame:
        """The next frame, once exposed and transferred (see the module docstring for the timing)."""
        half = self.settings.exposure_s / 2
        while True:
            slot, t = await self.grid.next(half + self.settings.latency_s)  # t: mid-exposure
            blur = self.settings.motion_blur
            start = self.truth.at(t - half if blur else t)
            end = self.truth.at(t + half) if blur else None
            if start is not None and (end is not None or not blur):
                return await clock.compute(self.render, t, start, end, slot)

    async def close(self) -> None:
        """Nothing to release."""

    def camera_pose(self, pose: TruthPose) -> tuple[np.ndarray, np.ndarray]:
        """(rotation optical -> NED (3x3), camera centre in NED (3,) m) for the vehicle ``pose``."""
        return optical_pose(self.mount, pose)

    def laser_hits(self, pose: TruthPose) -> tuple[np.ndarray, np.ndarray]:
        """Where the true laser beams of the vehicle at ``pose`` meet the world, as the renderer
        draws their dots: ((3, 3) NED points m, (3,) beam lengths m), row i = beam i, NaN for a beam
        that meets nothing. ValueError if the settings give no ``laser_beams``."""
        if self.lasers is None:
            raise ValueError(f"camera {self.camera_id}: no laser_beams in its settings")
        points, lengths, _ = self.lasers.hits(rotation_from_quat(pose.quat), np.asarray(pose.position_ned, float))
        return points, lengths

    def render(self, t_capture: float, start: TruthPose, end: TruthPose | None = None, sequence: int = 0) -> Frame:
        """The frame exposed while the vehicle moved from ``start`` to ``end`` (None: stood still at
        ``start``), stamped ``t_capture`` (daemon clock, s, mid-exposure)."""
        views = self.exposure_views(start, end)
        image = self.view(*views[0])
        for rotation, origin in views[1:]:
            image += self.view(rotation, origin)
        weight = self.settings.gain / len(views)
        image *= np.float32(weight)  # the mean over the exposure, times the gain
        if self.lasers is not None:
            image = cv2.merge((image, image, image))
            self.lasers.draw(image, views, sequence, weight)
        if self.settings.noise_sigma > 0:
            noise = np.random.default_rng((self.settings.seed, sequence)).standard_normal(image.shape, np.float32)
            image = cv2.scaleAdd(noise, self.settings.noise_sigma, image)
        pixels = cv2.add(image, 0.0, dtype=cv2.CV_8U)  # rounded, saturated to 0..255
        return Frame(self.camera_id, t_capture, pixels, sequence, self.settings.exposure_s)

    def exposure_views(self, start: TruthPose, end: TruthPose | None) -> list[tuple[np.ndarray, np.ndarray]]:
        """The camera poses (rotation optical -> NED, centre NED m) to average over the exposure."""
        r0, o0 = self.camera_pose(start)
        if end is None:
            return [(r0, o0)]
        r1, o1 = self.camera_pose(end)
        rvec = cv2.Rodrigues(r0.T @ r1)[0].ravel()  # from start to end, in the start's optical frame
        nearest = max(min(self.scene.nearest_distance(o0), self.scene.nearest_distance(o1)), NEAREST_SURFACE_MIN_M)
        motion_px = (np.linalg.norm(rvec) + np.linalg.norm(o1 - o0) / nearest) / self.rays.min_angle_rad
        k = int(np.clip(math.ceil(motion_px), 1, MAX_BLUR_SAMPLES))
        return [(r0 @ cv2.Rodrigues(rvec * f)[0], o0 + f * (o1 - o0)) for f in (np.arange(k) + 0.5) / k]

    def view(self, rotation: np.ndarray, origin: np.ndarray) -> np.ndarray:
        """The noiseless (H, W) float32 grey image of a camera at ``origin`` (NED, m) with
        ``rotation`` (optical -> NED) at one instant."""
        r = rotation.astype(np.float32)
        x, y, z = self.rays.x, self.rays.y, self.rays.z
        rays = tuple(r[i, 0] * x + r[i, 1] * y + r[i, 2] * z for i in range(3))
        image = self.scene.shade(origin, rays, self.rays.footprint_k, functools.partial(self.window, rotation, origin))
        image[~self.rays.reached] = 0.0
        return image

    def window(self, rotation: np.ndarray, origin: np.ndarray, corners: np.ndarray) -> tuple[slice, slice] | None:
        """The image rows and columns (slices) that may show a flat convex polygon with (N, 3)
        ``corners`` (NED, m) to a camera at ``origin`` (NED, m) with ``rotation`` (optical -> NED);
        None if it is out of view. Conservative: every row and column holding a ray that passes
        within the bounding box (in normalised image coordinates) of the polygon's visible part."""
        front = in_front(((corners - origin) @ rotation), NEAR_M)  # optical frame
        if len(front) == 0:
            return None
        xy = front[:, :2] / front[:, 2:]
        box = np.array([*xy.min(axis=0), *xy.max(axis=0)])  # x_lo, y_lo, x_hi, y_hi

        def overlapping(spans: np.ndarray) -> np.ndarray:
            return np.flatnonzero((spans[:, 0] <= box[2]) & (spans[:, 1] >= box[0])
                                  & (spans[:, 2] <= box[3]) & (spans[:, 3] >= box[1]))

        rows, cols = overlapping(self.rays.row_spans), overlapping(self.rays.col_spans)
        if rows.size == 0 or cols.size == 0:
            return None
        return slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1)


def optical_pose(mount: Mount, pose: TruthPose) -> tuple[np.ndarray, np.ndarray]:
    """(rotation optical -> NED (3x3), camera centre in NED (3,) m) of a camera on ``mount`` for
    the vehicle ``pose`` (OpenCV's optical frame, drivers/mount.py ``OPTICAL_TO_SENSOR``)."""
    rotation, origin = mount.sensor_to_world(pose.position_ned, pose.quat)
    return rotation @ OPTICAL_TO_SENSOR, origin


def in_front(polygon: np.ndarray, near: float) -> np.ndarray:
    """The (M, 3) corners of the part of the flat convex ``polygon`` (N, 3) (optical frame, m) with
    z >= ``near`` (m); empty if none."""
    out = []
    for p, q in zip(polygon, np.roll(polygon, -1, axis=0)):
        if p[2] >= near:
            out.append(p)
        if (p[2] >= near) != (q[2] >= near):
            out.append(p + (q - p) * (near - p[2]) / (q[2] - p[2]))
    return np.array(out).reshape(-1, 3)
