"""Laser dots in the simulated camera's image: where the vehicle's laser beams meet the world.

Frames and units: world LOCAL_NED (metres, the floor at z = 0, companion/world.py); body FRD;
OpenCV's optical frame and pixels (u, v) = (column, row), integers at pixel centres
(companion/calibration.py). A camera view is (rotation optical -> NED, camera centre NED m), as
:meth:`sitl.camera_sim.SimulatedCamera.exposure_views` gives it.

Model of one dot, for each view of the exposure (so that a dot smears with motion blur as the
scene does):

- the vehicle's body pose is the camera's undone through its mount (camera and beams are one
  rigid body); each beam of the TRUE rig (companion/laser_beams.py) meets the first
  thing along it (:meth:`sitl.camera_scene.Scene.cast`): the floor, an obstacle's top or side, a
  wall; nothing within the scene's range (a beam pointing up into the open): no dot;
- the camera sees the dot unless something lies between them (the ray from the camera meets a
  surface more than :data:`OCCLUSION_TOLERANCE_M` short of it), the dot lies behind it, outside
  the image or where the lens model does not reach (the dot's centre decides: the tail of a dot
  centred just outside the image is not drawn);
- shape: the beam's cross-section is a Gaussian of 1/e^2 diameter ``spot_m`` (1-sigma
  ``spot_m / 4``); on the surface it stretches by 1 / cos(incidence) along the beam's trace
  (at most 1 / :data:`MIN_COS_INCIDENCE`); that ellipse is projected through the lens's local
  Jacobian (finite differences of CameraCalibration.project, the renderer's lens model) and
  blurred by the optics, a Gaussian of ``bloom_px``: a (2, 2) pixel covariance;
- brightness: ``peak`` grey levels added at the dot's centre, whatever its range and size (a
  laser dot outshines the scene by far: its core saturates near or far);
- speckle: each dot's apparent centre moves by a Gaussian of ``speckle_px`` per axis, one draw
  per dot and frame from a generator seeded with (seed, frame sequence, :data:`SPECKLE_STREAM`);
- colour: added to the B, G, R channels in the proportions :data:`LASER_BGR`, before the camera's
  gain, noise and saturation (sitl/camera_sim.py); drawn only within :data:`SPOT_WINDOW_SIGMAS`
  of the centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.calibration import CameraCalibration
from companion.laser_beams import BEAMS, BeamRig
from drivers.mount import OPTICAL_TO_SENSOR, Mount
from sitl.camera_scene import Scene

LASER_BGR = np.array([0.04, 0.12, 1.0], np.float32)  # a red laser on a colour sensor: share of B, G, R
SPOT_WINDOW_SIGMAS = 4.0  # a dot is drawn out to this many standard deviations from its centre
OCCLUSION_TOLERANCE_M = 1e-3  # a surface this much nearer than the dot along the camera's ray does not hide it
MIN_COS_INCIDENCE = 0.05  # a grazing beam's spot stretches by at most 1 / this
SPECKLE_STREAM = 1  # third seed word of the speckle generator (the pixel noise's seed has two)


@dataclass(frozen=True)
class Spot:
    """One dot in the image: ``centre`` (u, v) px, ``covariance`` (2, 2) px^2, ``peak`` grey levels."""

    centre: np.ndarray
    covariance: np.ndarray
    peak: float


@dataclass(frozen=True)
class LaserSpots:
    """The dots of the true beam ``rig`` (body FRD) in the images of a camera on ``mount`` with
    ``calibration``, seeing ``scene``; ``reached`` (H, W) marks the pixels its lens model reaches.
    ``spot_m``: 1/e^2 beam diameter, m; ``peak``: grey levels at a dot's centre; ``speckle_px``,
    ``bloom_px``: 1-sigma speckle displacement and optical blur, px; ``seed``: of the speckle."""

    rig: BeamRig
    scene: Scene
    calibration: CameraCalibration
    reached: np.ndarray
    mount: Mount
    spot_m: float
    peak: float
    speckle_px: float
    bloom_px: float
    seed: int

    def hits(self, rotation: np.ndarray, position: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where the beams of a body at ``position`` (NED, m) with ``rotation`` (body FRD -> NED)
        first meet something: ((3, 3) points NED m, (3,) beam lengths m, (3, 3) unit surface
        normals NED), row i = beam i; NaN rows for a beam that meets nothing."""
        origins = position + self.rig.origins @ rotation.T
        directions = self.rig.directions @ rotation.T
        lengths, normals = np.empty(BEAMS), np.empty((BEAMS, 3))
        for origin in np.unique(origins, axis=0):  # one trace per distinct origin
            beams = np.flatnonzero((origins == origin).all(axis=1))
            lengths[beams], normals[beams] = self.scene.cast(origin, directions[beams])
        return origins + lengths[:, None] * directions, lengths, normals

    def draw(self, image: np.ndarray, views: list[tuple[np.ndarray, np.ndarray]], sequence: int,
             weight: float) -> None:
        """Add to the (H, W, 3) float32 BGR ``image`` the dots each camera view (rotation optical
        -> NED, centre NED m) sees, times ``weight`` (the gain over the number of views), with the
        speckle of frame ``sequence``."""
        rng = np.random.default_rng((self.seed, sequence, SPECKLE_STREAM))
        speckle = rng.standard_normal((BEAMS, 2)) * self.speckle_px
        for rotation, origin in views:
            body_rotation = rotation @ (self.mount.rotation @ OPTICAL_TO_SENSOR).T
            points, _, normals = self.hits(body_rotation, origin - body_rotation @ self.mount.offset_m)
            seen = self.visible(origin, points)
            for beam in np.flatnonzero(seen):
                direction = self.rig.directions[beam] @ body_rotation.T
                spot = self.spot(rotation, origin, points[beam], direction, normals[beam])
                if spot is not None:
                    add_spot(image, self.reached, spot.centre + speckle[beam], spot.covariance, spot.peak * weight)

    def spot(self, rotation: np.ndarray, origin: np.ndarray, point: np.ndarray, direction: np.ndarray,
             normal: np.ndarray) -> Spot | None:
        """The dot at ``point`` (NED, m) on a surface with unit ``normal`` (NED), lit along the unit
        beam ``direction`` (NED), as the camera at ``origin`` (NED, m) with ``rotation`` (optical ->
        NED) sees it (:meth:`visible` tells whether something hides it); None if it is behind the
        camera, outside the image or where the lens model does not reach."""
        axes = footprint_axes(direction, normal, self.spot_m)
        samples = np.vstack((point, point + axes, point - axes))  # the centre, then +- each 1-sigma semi-axis
        pixels = self.calibration.project((samples - origin) @ rotation)
        if not (np.isfinite(pixels).all() and self.in_image(pixels[0])):
            return None
        jacobian = (pixels[1:3] - pixels[3:5]).T / 2.0  # columns: pixels per 1-sigma semi-axis
        return Spot(pixels[0], jacobian @ jacobian.T + np.eye(2) * self.bloom_px ** 2, self.peak)

    def visible(self, origin: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(N,) bool: whether each of the (N, 3) ``points`` (NED, m; NaN: no point) is there and
        nothing lies between it and the camera at ``origin`` (NED, m)."""
        seen = np.isfinite(points).all(axis=1)
        offsets = points[seen] - origin
        distances = np.linalg.norm(offsets, axis=1)
        nearest, _ = self.scene.cast(origin, offsets / distances[:, None])
        seen[seen] = ~(nearest < distances - OCCLUSION_TOLERANCE_M)  # NaN (nothing met): seen
        return seen

    def in_image(self, pixel: np.ndarray) -> bool:
        """Whether ``pixel`` (u, v) lies in the image on a pixel the lens model reaches."""
        u, v = (int(math.floor(c + 0.5)) for c in pixel)
        height, width = self.reached.shape
        return 0 <= u < width and 0 <= v < height and bool(self.reached[v, u])


def footprint_axes(direction: np.ndarray, normal: np.ndarray, spot_m: float) -> np.ndarray:
    """(2, 3) NED vectors (m): the 1-sigma semi-axes of the spot of a beam along the unit
    ``direction`` with 1/e^2 diameter ``spot_m`` (m) on a surface with unit ``normal``: along the
    beam's trace on the surface (stretched by 1 / cos(incidence)), then across it."""
    sigma = spot_m / 4.0
    along = direction - (direction @ normal) * normal
    if np.linalg.norm(along) < 1e-9:  # square on: any direction in the surface
        along = np.cross(normal, (1.0, 0.0, 0.0) if abs(normal[0]) < 0.9 else (0.0, 1.0, 0.0))
    along /= np.linalg.norm(along)
    stretch = 1.0 / max(abs(float(direction @ normal)), MIN_COS_INCIDENCE)
    return np.array([along * sigma * stretch, np.cross(normal, along) * sigma])


def add_spot(image: np.ndarray, reached: np.ndarray, centre: np.ndarray, covariance: np.ndarray,
             amplitude: float) -> None:
    """Add ``amplitude * exp(-d' C^-1 d / 2)`` (d: pixel minus ``centre`` (u, v), C: ``covariance``
    px^2) times :data:`LASER_BGR` to the (H, W, 3) float32 ``image``, within
    :data:`SPOT_WINDOW_SIGMAS` of the centre, on the pixels the lens ``reached`` (H, W)."""
    half = SPOT_WINDOW_SIGMAS * np.sqrt(np.diag(covariance))
    lo = np.maximum(np.ceil(centre - half), 0).astype(int)
    hi = np.minimum(np.floor(centre + half), (image.shape[1] - 1, image.shape[0] - 1)).astype(int)
    if np.any(lo > hi):
        return
    du = np.arange(lo[0], hi[0] + 1) - centre[0]
    dv = (np.arange(lo[1], hi[1] + 1) - centre[1])[:, None]
    inverse = np.linalg.inv(covariance)
    exponent = inverse[0, 0] * du * du + 2.0 * inverse[0, 1] * du * dv + inverse[1, 1] * dv * dv
    window = slice(lo[1], hi[1] + 1), slice(lo[0], hi[0] + 1)
    level = (amplitude * np.exp(-0.5 * exponent) * reached[window]).astype(np.float32)
    image[window] += level[..., None] * LASER_BGR
