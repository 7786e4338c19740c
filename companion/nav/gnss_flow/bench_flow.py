"""Frames of a forward camera over textured ground, and the timings and accuracy of the grid
Lucas-Kanade flow on them (for ``companion bench``; the tests use the frames too).

The scene (issue 15's fixed wing): flat ground 100 m below a forward-looking 640 x 480 pinhole
camera with a 90 x 90 deg field of view (fx = 320 px, fy = 240 px, no lens distortion) along body
x, the image upright (drivers.mount.OPTICAL_TO_SENSOR), flying at 20 m/s and filmed at 10 Hz in a
gentle banked turn. The ground is a procedural texture with a 1/f amplitude spectrum (about equal
contrast at every scale, 0.25 m texels, repeating every 512 m), mip-mapped by cropping its
spectrum (so far and grazing ground does not alias) and drawn by ``cv2.warpPerspective`` of the
ground-to-image homography; above the horizon a smooth sky. Each frame gets Gaussian pixel noise.
The exact flow of a ground point is the homography from the earlier image to the later one.

Frames and units: world NED (x north, y east, z down), metres; body FRD; camera optical frame (x
right, y down, z forward); pixels (u, v) = (column, row); angles in degrees where named ``_deg``.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from companion.frames import rotation_from_euler
from companion.nav.gnss_flow.flow import GridFlow, derotate, focus_of_expansion, grid_flow
from companion.timing import time_stage
from drivers.mount import OPTICAL_TO_SENSOR

WIDTH, HEIGHT = 640, 480  # px
K = np.array([[320.0, 0.0, 319.5], [0.0, 240.0, 239.5], [0.0, 0.0, 1.0]])  # 90 x 90 deg pinhole
AGL_M, SPEED_MPS, RATE_HZ = 100.0, 20.0, 10.0
ATTITUDE_DEG = (10.0, 3.0, 30.0)  # roll, pitch, yaw of the earlier frame
RATES_RADPS = np.array([0.02, 0.01, 0.06])  # body p, q, r (a gentle turn)
TEXEL_M = 0.25  # finest texel of the ground texture
TEXTURE_TEXELS = 2048  # side of the (repeating) texture
NOISE_GREY = 2.0  # sigma of the pixel noise, grey levels
SKY_GREY = (235.0, 200.0)  # sky brightness at the zenith and at the horizon
MIN_DEPRESSION_DEG = 4.0  # ground points scored: this far below the horizon (the window clear of it)
FRAMES = 8  # distinct frames the bench cycles through


@functools.lru_cache(maxsize=1)
def _texture_levels() -> tuple[np.ndarray, ...]:
    """The ground texture's mip levels (float32 grey, 0..255 about a mean of 128): level k has
    TEXTURE_TEXELS / 2**k texels a side, its texel i at level-0 texel i * 2**k, each the
    spectrum's lowest frequencies cropped from the same 1/f noise (exactly band-limited)."""
    n = TEXTURE_TEXELS
    rng = np.random.default_rng(15)
    f = np.fft.fftfreq(n)
    radius = np.hypot(f[:, None], f[None, :])
    spectrum = (rng.normal(size=(n, n)) + 1j * rng.normal(size=(n, n))) / np.maximum(radius, 1.0 / n)
    spectrum[0, 0] = 0.0
    base = np.fft.ifft2(spectrum).real
    scale = 45.0 / base.std()  # 45 grey levels of contrast at level 0
    levels = []
    size = n
    while size >= 8:
        keep = np.fft.fftshift(spectrum)[(n - size) // 2:(n + size) // 2, (n - size) // 2:(n + size) // 2]
        level = np.fft.ifft2(np.fft.ifftshift(keep)).real * (size / n) ** 2 * scale + 128.0
        levels.append(level.astype(np.float32))
        size //= 2
    return tuple(levels)


@dataclass(frozen=True)
class Pose:
    """A camera pose: ``cam_to_ned`` (3x3, v_ned = cam_to_ned @ v_cam) at ``position_ned`` (m)."""

    cam_to_ned: np.ndarray
    position_ned: np.ndarray


def flight_poses(n: int, attitude_deg: tuple[float, float, float] = ATTITUDE_DEG,
                 rates_radps: np.ndarray = RATES_RADPS) -> list[Pose]:
    """``n`` camera poses 1 / RATE_HZ s apart: level flight AGL_M above the ground at SPEED_MPS
    along the yaw of ``attitude_deg`` (roll, pitch, yaw of the first pose), the body turning at
    ``rates_radps`` (body p, q, r, rad/s)."""
    body = rotation_from_euler(*np.radians(attitude_deg))
    turn, _ = cv2.Rodrigues(np.asarray(rates_radps, dtype=float) / RATE_HZ)
    yaw = math.radians(attitude_deg[2])
    step = SPEED_MPS / RATE_HZ * np.array([math.cos(yaw), math.sin(yaw), 0.0])
    poses = []
    for k in range(n):
        poses.append(Pose(body @ OPTICAL_TO_SENSOR, np.array([0.0, 0.0, -AGL_M]) + k * step))
        body = body @ turn
    return poses


def image_from_ground(pose: Pose) -> np.ndarray:
    """The homography (3x3) from level-0 texture coordinates (east / TEXEL_M, north / TEXEL_M)
    of the ground plane z = 0 to the camera's pixels."""
    n, e, d = pose.position_ned
    to_ground = np.array([[0.0, TEXEL_M, -n], [TEXEL_M, 0.0, -e], [0.0, 0.0, -d]])  # (N, E, 0) - C
    return K @ pose.cam_to_ned.T @ to_ground


def render(pose: Pose, rng: np.random.Generator, noise_grey: float = NOISE_GREY) -> np.ndarray:
    """The grey uint8 image (HEIGHT, WIDTH) from ``pose``: trilinear mip-mapped ground (the level
    from the largest side of each pixel's footprint on the texture, fading to the texture's mean
    grey beyond the coarsest level), sky above the horizon,
    Gaussian noise of sigma ``noise_grey`` grey levels from ``rng``."""
    levels = _texture_levels()
    to_tex = np.linalg.inv(image_from_ground(pose))
    u, v = np.meshgrid(np.arange(WIDTH, dtype=float), np.arange(HEIGHT, dtype=float))
    x, y, w = (to_tex[i, 0] * u + to_tex[i, 1] * v + to_tex[i, 2] for i in range(3))
    # the Jacobian of the pixel -> texel map, its columns' lengths bound the footprint
    du = np.hypot(to_tex[0, 0] - x / w * to_tex[2, 0], to_tex[1, 0] - y / w * to_tex[2, 0])
    dv = np.hypot(to_tex[0, 1] - x / w * to_tex[2, 1], to_tex[1, 1] - y / w * to_tex[2, 1])
    lod = np.clip(np.log2(np.maximum(np.maximum(du, dv) / np.abs(w), 1e-9)), 0.0, len(levels))
    ground = 128.0 * np.clip(lod - (len(levels) - 1), 0.0, 1.0)  # beyond the coarsest level: the mean
    for k, level in enumerate(levels):
        weight = np.clip(1.0 - np.abs(lod - k), 0.0, 1.0)
        if not weight.any():
            continue
        to_level = np.diag([0.5 ** k, 0.5 ** k, 1.0]) @ to_tex
        warped = cv2.warpPerspective(level, to_level, (WIDTH, HEIGHT), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_WRAP)
        ground += weight * warped
    rays = np.stack((u, v, np.ones_like(u)), axis=-1) @ (pose.cam_to_ned @ np.linalg.inv(K)).T
    sin_dep = rays[..., 2] / np.linalg.norm(rays, axis=-1)  # > 0 below the horizon
    sky = SKY_GREY[1] + (SKY_GREY[0] - SKY_GREY[1]) * np.clip(-sin_dep, 0.0, 1.0)
    image = np.where(sin_dep > 0.0, ground, sky) + rng.normal(0.0, noise_grey, ground.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def exact_flow(points_px: np.ndarray, earlier: Pose, later: Pose) -> tuple[np.ndarray, np.ndarray]:
    """(flows (N, 2) px, scored (N,) bool): the exact flow of the ground seen at ``points_px``
    (N, 2) from ``earlier`` to ``later``, and which points are ground at least
    MIN_DEPRESSION_DEG below the horizon (elsewhere the flow is NaN)."""
    pts = np.asarray(points_px, dtype=float)
    rays = np.column_stack((pts, np.ones(len(pts)))) @ (earlier.cam_to_ned @ np.linalg.inv(K)).T
    scored = rays[:, 2] / np.linalg.norm(rays, axis=1) >= math.sin(math.radians(MIN_DEPRESSION_DEG))
    H = image_from_ground(later) @ np.linalg.inv(image_from_ground(earlier))
    moved = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), H).reshape(-1, 2)
    return np.where(scored[:, None], moved - pts, np.nan), scored


@dataclass(frozen=True)
class FlowAccuracy:
    """LK flow against the exact flow on the scored ground points (see :func:`exact_flow`)."""

    median_px: float  # median endpoint error of the valid points, px
    p90_px: float  # 90th percentile, px
    valid_fraction: float  # scored points LK marks valid


def flow_accuracy(flows: list[GridFlow], poses: list[Pose]) -> FlowAccuracy:
    """Accuracy over consecutive pairs: ``flows[i]`` from the frame at ``poses[i]`` to the next."""
    errors, valid = [], []
    for flow, earlier, later in zip(flows, poses, poses[1:]):
        truth, scored = exact_flow(flow.points_px, earlier, later)
        ok = scored & flow.valid
        errors.append(np.linalg.norm(flow.flows_px[ok] - truth[ok], axis=1))
        valid.append(flow.valid[scored])
    err = np.concatenate(errors)
    return FlowAccuracy(float(np.median(err)), float(np.percentile(err, 90)), float(np.concatenate(valid).mean()))


def bench_frames(n: int = FRAMES, seed: int = 0) -> tuple[list[Pose], list[np.ndarray]]:
    """``n`` consecutive poses of the flight and their rendered frames (noise from ``seed``)."""
    rng = np.random.default_rng(seed)
    poses = flight_poses(n)
    return poses, [render(pose, rng) for pose in poses]


def run_flow_bench(repeat: int) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:
    """({stage: (median ms, p99 ms)}, {figure: text}) on the bench frames: the grid flow of each
    consecutive pair (forward and backward), the FOE of one pair's valid flow derotated by the
    true body rates, and the flow's accuracy over all pairs."""
    poses, frames = bench_frames()
    pairs: Iterator[tuple[np.ndarray, np.ndarray]] = itertools.cycle(list(zip(frames, frames[1:])))
    flow = grid_flow(frames[0], frames[1])
    focal = np.diag(K)[:2]
    points_n = (flow.points_px - K[:2, 2]) / focal
    trans_n = derotate(points_n, flow.flows_px / focal, RATES_RADPS, 1.0 / RATE_HZ, OPTICAL_TO_SENSOR)
    trans_n[~flow.valid] = np.nan
    stages = {
        "gnss_flow.lk 45x45 fwd+bwd (640x480)": lambda: grid_flow(*next(pairs)),
        "gnss_flow.foe (RANSAC + least squares, 45x45)": lambda: focus_of_expansion(points_n, trans_n),
    }
    timings = {name: time_stage(fn, repeat) for name, fn in stages.items()}
    accuracy = flow_accuracy([grid_flow(a, b) for a, b in zip(frames, frames[1:])], poses)
    figures = {f"LK flow vs exact ({len(frames) - 1} pairs, ground >= {MIN_DEPRESSION_DEG:g} deg below the horizon)":
               f"endpoint error median {accuracy.median_px:.3f} px, p90 {accuracy.p90_px:.3f} px, "
               f"{100 * accuracy.valid_fraction:.1f} % valid"}
    return timings, figures
