"""Simulated optic-flow sensor (``kind: flow, backend: sim``): the GNSS + optic-flow seed's
synthetic flow map (Roberts et al. 2005, Table 1: 45 x 45 flow over a 90 x 90 deg field of view,
+/-2.5 deg "introduced into the angle of the flow line"), from simulator ground truth.

Geometry: a pinhole camera on the sensor's ``mount`` (body-fixed; the seed's looks forward along
body x: ``rpy_deg [0, 0, 0]``), OpenCV's optical frame (drivers/mount.py ``OPTICAL_TO_SENSOR``).
The grid is ``grid`` = [columns, rows] points spread evenly over the image plane across
``fov_deg`` = [horizontal, vertical] (normalised x from -tan(h/2) to tan(h/2), edges included, y
likewise). Each grid ray of the earlier view is intersected with the flat ground (the world's
floor, NED z = ``ground_down_m``, 0 by README "Frames and time"; walls and obstacles are not
seen), and that ground point projected into the later view: the exact motion field of the
truth's motion between the two instants, in normalised image coordinates
(:class:`companion.messages.FlowField`). A ray that does not go down to the ground in front of the
camera (the sky) or whose ground point is behind the later view is invalid.

Noise, the seed's: each valid flow vector's direction turned by an angle drawn uniformly in
[-``angle_noise_deg``, ``angle_noise_deg``] (its length kept), from a generator seeded with
(``seed``, sequence).

Timing: fields at ``t0 + k / rate_hz`` (daemon clock, s) from :meth:`SimulatedFlowSensor.open`;
field k spans [t_k - 1 / rate_hz, t_k] (``t_earlier``, ``t_capture``), the truth at both
(:meth:`sitl.truth.TruthSource.at`), and arrives ``latency_s`` after its later instant. A reader
more than a period late skips to the latest due field; a field without truth at either instant
yields nothing. No I/O beyond the truth source.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.messages import FlowField
from companion.schema import meta
from drivers.base import Backend
from drivers.mount import Mount
from sitl.camera_sim import optical_pose
from sitl.capture_grid import CaptureGrid
from sitl.truth import TruthLike, TruthPose


@dataclass(frozen=True)
class SimFlowSettings:
    """``settings:`` of a flow sensor with ``backend: sim`` (a companion.schema dataclass)."""

    rate_hz: float = field(default=10.0, metadata=meta(
        "Fields per second; each spans 1 / rate_hz (its earlier and later instants), Hz.", (0.5, 100)))
    grid: tuple[int, int] = field(default=(45, 45), metadata=meta(
        "Flow grid, [columns, rows] of points spread evenly over the image plane (seed: 45 x 45).", (2, 500)))
    fov_deg: tuple[float, float] = field(default=(90.0, 90.0), metadata=meta(
        "Field of view the grid spans, [horizontal, vertical] degrees (seed: 90 x 90).", (1, 170)))
    angle_noise_deg: float = field(default=2.5, metadata=meta(
        "Each flow vector's direction is turned by a uniform random angle within +/- this, degrees "
        "(seed: 2.5); its length is kept.", (0, 180)))
    latency_s: float = field(default=0.03, metadata=meta(
        "From a field's later instant to its delivery (the flow computation), seconds. At least the truth's "
        "period (SIM_STATE at 50 Hz: 0.02): a field rendered before the truth of its later instant has arrived "
        "takes the newest pose received instead, up to a period old.", (0, 1)))
    ground_down_m: float = field(default=0.0, metadata=meta(
        "NED down coordinate of the flat ground, metres (0: the world's floor).", (-10000, 10000)))
    seed: int = field(default=0, metadata=meta("Seed of the angle noise.", (0, 999999)))


def grid_points(grid: tuple[int, int], fov_deg: tuple[float, float]) -> np.ndarray:
    """(columns * rows, 2) normalised image points (x, y), row after row (x fastest), spread evenly
    across the field of view ``fov_deg`` = (horizontal, vertical) degrees, its edges included."""
    half_x, half_y = (math.tan(math.radians(a) / 2) for a in fov_deg)
    xs, ys = np.linspace(-half_x, half_x, grid[0]), np.linspace(-half_y, half_y, grid[1])
    return np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)


def ground_motion_field(points_n: np.ndarray, earlier: tuple[np.ndarray, np.ndarray],
                        later: tuple[np.ndarray, np.ndarray],
                        ground_down_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The exact flow over flat ground: (flows (N, 2) normalised, NaN where invalid; valid (N,)
    bool). ``points_n`` (N, 2) normalised points of the earlier view; ``earlier`` and ``later``
    the camera poses (rotation optical -> NED (3x3), centre NED (3,) m); the ground is the plane
    NED z = ``ground_down_m``. Valid where the earlier ray meets the ground in front of the camera
    and that ground point lies in front of the later camera."""
    (r0, o0), (r1, o1) = earlier, later
    rays = np.column_stack((points_n, np.ones(len(points_n)))) @ r0.T  # NED
    below = ground_down_m - o0[2]  # m, positive with the camera above the ground
    down = rays[:, 2]
    hits = (down > 0) & (below > 0)
    ground = o0 + rays * np.where(hits, below / np.where(hits, down, 1.0), np.nan)[:, None]
    in_later = (ground - o1) @ r1  # optical frame of the later view
    valid = hits & (in_later[:, 2] > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        flows = np.where(valid[:, None], in_later[:, :2] / in_later[:, 2:] - points_n, np.nan)
    return flows, valid


def turn_directions(flows_n: np.ndarray, angles_rad: np.ndarray) -> np.ndarray:
    """(N, 2): each flow vector of ``flows_n`` (N, 2) turned by its angle in ``angles_rad`` (N,),
    rad (positive from image x towards image y), its length kept."""
    c, s = np.cos(angles_rad), np.sin(angles_rad)
    x, y = flows_n[:, 0], flows_n[:, 1]
    return np.column_stack((c * x - s * y, s * x + c * y))


class SimulatedFlowSensor(Backend[FlowField]):
    """An optic-flow sensor on ``mount`` seeing the flat ground from ``truth``'s poses."""

    def __init__(self, sensor_id: str, settings: SimFlowSettings, mount: Mount, truth: TruthLike) -> None:
        self.sensor_id = sensor_id
        self.settings = settings
        self.mount = mount
        self.truth = truth
        self.points_n = grid_points(settings.grid, settings.fov_deg)
        self.grid = CaptureGrid(1.0 / settings.rate_hz)
        self.description = (f"simulated flow {settings.grid[0]}x{settings.grid[1]} over "
                            f"{settings.fov_deg[0]:g}x{settings.fov_deg[1]:g} deg at {settings.rate_hz:g} Hz")

    async def open(self) -> None:
        """Start the field grid at the current daemon time."""
        self.grid.start()

    async def read(self) -> FlowField:
        """The next field, ``latency_s`` after its later instant (see the module docstring)."""
        while True:
            slot, t = await self.grid.next(self.settings.latency_s)
            t_earlier = t - self.grid.period_s
            earlier, later = self.truth.at(t_earlier), self.truth.at(t)
            if earlier is not None and later is not None:
                return self.field(t_earlier, t, earlier, later, slot)

    async def close(self) -> None:
        """Nothing to release."""

    def field(self, t_earlier: float, t_capture: float, earlier: TruthPose, later: TruthPose,
              sequence: int = 0) -> FlowField:
        """The field of the vehicle moving from ``earlier`` (at ``t_earlier``) to ``later`` (at
        ``t_capture``), daemon clock s, with the angle noise of ``sequence``."""
        s = self.settings
        flows, valid = ground_motion_field(self.points_n, optical_pose(self.mount, earlier),
                                           optical_pose(self.mount, later), s.ground_down_m)
        if s.angle_noise_deg > 0:
            rng = np.random.default_rng((s.seed, sequence))
            limit = math.radians(s.angle_noise_deg)
            flows = turn_directions(flows, rng.uniform(-limit, limit, len(flows)))
        return FlowField(self.sensor_id, t_earlier, t_capture, self.points_n.copy(), flows, valid, sequence)
