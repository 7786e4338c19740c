"""The ``laser_dots`` pipeline: the three-laser-dot pose on a downward camera, fused with the IMU.

Data flow (in the daemon's event loop, no I/O here):

- the camera's newest frame, once per nav cycle -> the three dots (:mod:`.detect`: which beam made
  which dot, and each beam's length by structured-light triangulation) and the floor markers
  (:mod:`.floor`: the image-to-floor homography) -> the dots on the floor (NED m) -> the 6-DOF pose
  (:mod:`.geometry`: the seed's 90-degree closed form or the calibrated general solver) with its
  covariance from the pixel and marker noise -> fusion position (3-D) and yaw corrections at the
  frame's capture time;
- without a marker in view, the dots alone still give the height above the floor and roll and
  pitch: a height correction, a :class:`RangeEstimate` (DISTANCE_SENSOR) and an
  :class:`AttitudeEstimate` (the cross-check; yaw NaN: not measured);
- the IMU's samples -> fusion prediction (companion/nav/fusion.py, as the lidar pipeline);
- every nav cycle: the fused state -> a :class:`PoseEstimate` whose roll and pitch are the newest
  measured ones carried forward by the autopilot's attitude change since that frame.

A fix is refused (the pipeline degrades, then loses the pose, with the reason) rather than
trusted when it disagrees with itself: a dot whose triangulated beam length differs from the
length the floor solution needs (a dot on a table, a step), the beam-matrix attitude and the
P3P rotation disagreeing, a solution tilted beyond ``max_tilt_deg`` or outside the height range.

Frames: world LOCAL_NED (the floor is z = 0), body FRD, the camera placed by its sensor mount
(``sensors.<camera>.mount``); times on the daemon clock, s.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from companion.calibration import CameraCalibration, load_calibration
from companion.frames import rotation_from_euler, wrap_pi
from companion.health import Health, State
from companion.laser_beams import BeamRigConfig
from companion.messages import AttitudeEstimate, Estimate, Frame, PoseEstimate, RangeEstimate
from companion.nav.fusion import FusionFilter
from companion.nav.fusion_io import FusedOutput, ImuFeed, to_pose_estimate
from companion.nav.laser_dots import geometry
from companion.nav.laser_dots.frame_pose import FramePoseParams, FramePoser, FrameResult
from companion.pipeline import PipelineContext
from companion.plugins import register_pipeline
from companion.schema import meta
from companion.timing import Timings
from companion.world import FloorMarker, World, load_world
from drivers.mount import OPTICAL_TO_SENSOR, Mount

STREAM = "laser_dots"
# One frame without a pose (a dot hidden for a moment, a speckle outlier refused) leaves the fusion
# coasting on the IMU for a frame period: the pipeline reports degraded from this many in a row.
DEGRADED_AFTER_FRAMES = 3


@dataclass
class LaserDotsConfig:
    """``pipelines.laser_dots``: the three-laser-dot pose (Kara Mohamed et al.) on a downward camera."""

    camera: str = field(metadata=meta("Name (in `sensors`) of the downward camera (kind camera, colour frames)."))
    calibration: str = field(metadata=meta(
        "The camera's intrinsics (OpenCV or ROS YAML, relative to this file), for the frames' resolution."))
    world: str = field(metadata=meta("World YAML whose floor_markers map the dots to the floor, relative to this file."))
    imu_sensor: str = field(default="imu", metadata=meta("Name (in `sensors`) of the IMU the fusion predicts with."))
    beams: BeamRigConfig = field(default_factory=BeamRigConfig, metadata=meta(
        "The laser beams in body FRD: nominal, or calibrated (`companion laser-dots calibrate`)."))
    method: Literal["general", "closed_form"] = field(default="general", metadata=meta(
        "general: P3P on the (calibrated) beams with solution selection; closed_form: the seed's eqs. 10-14, "
        "which assume three beams at exactly 90 degrees from one point."))
    height_range_m: tuple[float, float] = field(default=(0.0, 2.5), metadata=meta(
        "Heights of the body origin above the floor the rig is used at, m (0: resting on the floor): a solution "
        "outside is refused; check-config warns if a dot leaves the image within it.", (0, 50)))
    max_tilt_deg: float = field(default=15.0, metadata=meta(
        "Largest tilt (roll and pitch combined) of a solution, and of check-config's field-of-view envelope.", (0, 60)))
    dot_sigma_px: float = field(default=0.5, metadata=meta(
        "1-sigma error of a dot's centroid, px (laser speckle dominates): the covariance's input.", (0.01, 20)))
    length_gate_sigmas: float = field(default=5.0, metadata=meta(
        "A dot whose triangulated beam length differs from the floor solution's by more sigmas is not on the floor "
        "(a table, a step): the fix is refused.", (1, 100)))
    max_cross_check_deg: float = field(default=2.0, metadata=meta(
        "The beam-matrix attitude and the P3P rotation may differ this much; more refuses the fix.", (0.01, 90)))

    def validate(self) -> tuple[str, str] | None:
        low, high = self.height_range_m
        if low >= high:
            return "height_range_m", "give [lowest, highest] with lowest < highest"
        if self.method == "closed_form" and self.beams.directions is not None:
            return "method", "closed_form assumes the nominal 90-degree rig: use general with calibrated beams"
        if self.method == "closed_form" and abs(self.beams.angle_deg - 90.0) > geometry.RIGHT_ANGLE_TOLERANCE_DEG:
            return "beams.angle_deg", (f"closed_form solves beams at 90 degrees (within "
                                       f"{geometry.RIGHT_ANGLE_TOLERANCE_DEG:g}): use method general")
        return None

    def sensor_inputs(self) -> dict[str, str]:
        return {"camera": "camera", "imu_sensor": "imu"}

    def moved(self, raw: dict[str, Any], offset: tuple[float, float], move_map: Callable[[str], str]) -> dict[str, Any]:
        """This section for a local frame whose origin moved: the world replaced by ``move_map(path)``."""
        return {**raw, "world": move_map(self.world)}


def frame_poser(section: LaserDotsConfig, calibration: CameraCalibration, camera_mount: Mount,
                markers: tuple[FloorMarker, ...]) -> FramePoser:
    """The per-frame solver a ``pipelines.laser_dots`` section describes, for a camera of
    ``calibration`` on ``camera_mount`` over a floor with ``markers``."""
    params = FramePoseParams(section.method, section.height_range_m, section.max_tilt_deg, section.dot_sigma_px,
                             section.length_gate_sigmas, section.max_cross_check_deg)
    return FramePoser(section.beams.rig(), calibration, camera_mount.rotation @ OPTICAL_TO_SENSOR,
                      camera_mount.offset_m, markers, params)


@dataclass
class LaserDotsStats:
    frames: int = 0
    skipped_frames: int = 0  # overtaken by a newer frame before the nav loop got to them
    pose_fixes: int = 0  # full 6-DOF fixes given to the fusion
    height_fixes: int = 0  # dots without a marker: height, roll and pitch only
    refused: dict[str, int] = field(default_factory=dict)  # fixes refused, per reason


class LaserDotsPipeline:
    """The three-laser-dot pose; see the module docstring."""

    name = "laser_dots"
    telemetry_streams = (STREAM,)

    def __init__(self, cfg: LaserDotsConfig, calibration: CameraCalibration, world: World, camera_mount: Mount,
                 health: Health) -> None:
        self.cfg = cfg
        self.world = world
        self.health = health
        self._image_size = (calibration.width, calibration.height)
        self.poser = frame_poser(cfg, calibration, camera_mount, world.floor_markers)
        self.fusion = FusionFilter()
        self.output = FusedOutput(self.fusion, health, "nav:laser_dots:fusion")
        self.stats = LaserDotsStats()
        self.timings = {"laser_dots": Timings(), "fusion": Timings()}
        self._frame: Frame | None = None
        self.imu = ImuFeed()
        self._measured: tuple[tuple[float, float], tuple[float, float, float]] | None = None  # (roll, pitch), autopilot euler then
        self._previous_pixels: np.ndarray | None = None
        self._previous_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._frames_without_pose = 0
        self._attitude_cov = np.full((2, 2), np.nan)  # of the newest measured roll, pitch, rad^2
        self._pending: list[Estimate] = []  # range and attitude estimates of this cycle's frame
        self.last_result: tuple[float, FrameResult] | None = None  # capture time (s), what that frame gave
        self._published: tuple[float, FrameResult] | None = None
        health.report("nav:laser_dots", State.LOST, "waiting for frames")

    # -- inputs (driver callbacks) ------------------------------------------------------

    def subscriptions(self) -> dict[str, Callable[[Any], None]]:
        return {self.cfg.camera: self.on_frame, self.cfg.imu_sensor: self.imu.add}

    def on_frame(self, frame: Frame) -> None:
        self.stats.frames += 1
        self.stats.skipped_frames += self._frame is not None
        self._frame = frame

    # -- the nav cycle --------------------------------------------------------------------

    def step(self, now: float) -> list[Estimate]:
        """Advance to daemon time ``now`` (s): this cycle's pose (while the fusion is healthy) and
        the range and attitude estimates of a frame processed now."""
        started = time.perf_counter()
        self.imu.predict(self.fusion)
        predicted = time.perf_counter()
        if self._frame is not None:
            self._process(self._frame)
            self._frame = None
            self.timings["laser_dots"].add((time.perf_counter() - predicted) * 1e3)
        resumed = time.perf_counter()
        out, self._pending = self._pending, []
        estimate = self._output(now)
        self.timings["fusion"].add((predicted - started + time.perf_counter() - resumed) * 1e3)
        return out if estimate is None else [estimate, *out]

    def _process(self, frame: Frame) -> None:
        attitude = self.imu.euler_at(frame.t_capture)  # the autopilot's, when the frame was exposed
        result = self.poser.process(frame.image, rotation_from_euler(*attitude), self._previous_pose,
                                    self._previous_pixels)
        found = result.dots.found
        self._previous_pixels = np.where(found[:, None], result.dots.pixels, np.nan) if found.any() else None
        if result.kind == "pose":
            self._correct_pose(frame.t_capture, result, attitude)
        elif result.kind == "tilt":
            self._correct_tilt(frame.t_capture, result, attitude)
        else:
            key = result.reason.split(":")[0]
            self.stats.refused[key] = self.stats.refused.get(key, 0) + 1
        self._frames_without_pose = 0 if result.kind == "pose" else self._frames_without_pose + 1
        if self._frames_without_pose >= DEGRADED_AFTER_FRAMES:
            self.health.report("nav:laser_dots", State.DEGRADED, result.reason)
        self.last_result = (frame.t_capture, result)

    def _correct_pose(self, t_capture: float, result: FrameResult, attitude: tuple[float, float, float]) -> None:
        solution, cov = result.solution, result.covariance
        assert solution is not None and cov is not None  # a "pose" result has both
        roll, pitch, yaw = (float(a) for a in solution.euler_rad)
        self.fusion.correct_position(t_capture, solution.position_ned, cov[:3, :3])
        self.fusion.correct_yaw(t_capture, yaw, float(cov[5, 5]))
        self._measured = ((roll, pitch), attitude)
        self._attitude_cov = cov[3:5, 3:5]
        self._previous_pose = (solution.rotation, solution.position_ned)
        self.stats.pose_fixes += 1
        self.health.report("nav:laser_dots", State.OK, result.reason)

    def _correct_tilt(self, t_capture: float, result: FrameResult, attitude: tuple[float, float, float]) -> None:
        """No marker in view: a height correction, DISTANCE_SENSOR and the attitude cross-check."""
        assert result.tilt is not None and result.tilt_covariance is not None  # a "tilt" result has both
        height, roll, pitch = result.tilt
        cov = result.tilt_covariance
        self.fusion.correct_height(t_capture, height, float(cov[0, 0]))
        self._measured = ((roll, pitch), attitude)
        self._attitude_cov = cov[1:, 1:]
        cos_tilt = math.cos(roll) * math.cos(pitch)  # the body's down axis against the floor normal
        low, high = self.cfg.height_range_m
        self._pending.append(RangeEstimate(t_capture, height / cos_tilt, float(cov[0, 0]) / cos_tilt ** 2,
                                           min_m=low, max_m=high, source=self.name))
        attitude_cov = np.diag([0.0, 0.0, math.inf])
        attitude_cov[:2, :2] = cov[1:, 1:]
        self._pending.append(AttitudeEstimate(t_capture, (roll, pitch, math.nan), attitude_cov, source=self.name))
        self.stats.height_fixes += 1

    def _output(self, now: float) -> PoseEstimate | None:
        fused = self.output.at(now)
        if fused is None:
            return None
        state, reset = fused
        roll, pitch = self._roll_pitch()
        estimate = to_pose_estimate(state, roll, pitch, reset=reset, source=self.name)
        estimate.pose_covariance[3:5, 3:5] = self._attitude_cov
        return estimate

    def _roll_pitch(self) -> tuple[float, float]:
        """The newest measured roll and pitch (rad) carried forward by the autopilot's change since."""
        assert self._measured is not None  # the fusion is healthy only after a fix
        (roll, pitch), then = self._measured
        return wrap_pi(roll + self.imu.euler[0] - then[0]), wrap_pi(pitch + self.imu.euler[1] - then[1])

    # -- telemetry --------------------------------------------------------------------------

    def snapshot(self) -> dict:
        """Counters for telemetry."""
        return {**dataclasses.asdict(self.stats),
                "fusion": {"gated": dict(self.fusion.stats.fixes_gated), "stale": self.fusion.stats.fixes_stale}}

    def telemetry(self, static_due: bool) -> dict[str, dict[str, Any]]:
        """The newest frame's detections and solution (once per frame)."""
        if self.last_result is None or self.last_result is self._published:
            return {}
        self._published = self.last_result
        t_capture, r = self.last_result
        solution = r.solution if r.kind == "pose" else None
        return {STREAM: {
            "t_capture": t_capture, "kind": r.kind, "status": r.reason, "image_size": self._image_size,
            "dots_px": r.dots.pixels, "dots_found": r.dots.found, "beam_lengths_m": r.dots.lengths_m,
            "extra_spots": r.dots.extra, "markers": list(r.markers),
            "marker_corners_px": r.marker_corners_px, "floor_dots_m": r.floor_dots,
            "candidates": 0 if r.solution is None else len(r.solution.candidates),
            "position_ned_m": None if solution is None else solution.position_ned,
            "euler_rad": None if solution is None else solution.euler_rad,
            "tilt": r.tilt,
        }}

    def operating_area(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The world's bounds, m (north, east)."""
        b = self.world.bounds
        return (float(b.min[0]), float(b.min[1])), (float(b.max[0]), float(b.max[1]))


def _load(ctx_load: Callable[..., Any], section: LaserDotsConfig) -> tuple[CameraCalibration, World]:
    calibration = ctx_load("pipelines.laser_dots.calibration", section.calibration, load_calibration)
    world = ctx_load("pipelines.laser_dots.world", section.world, load_world)
    return calibration, world


def _check_files(cfg: Any, section: LaserDotsConfig) -> None:
    _load(cfg.load_referenced, section)


FOV_HEIGHT_SAMPLES = 5  # heights checked across height_range_m
FOV_PROBLEMS_SHOWN = 3


def _advise(cfg: Any, section: LaserDotsConfig) -> list[str]:
    """The field-of-view constraint (seed eqs. 30-41, generalised by geometry.fov_problems): a
    warning when the camera loses a dot anywhere in the height range and tilt envelope."""
    calibration = cfg.load_referenced("pipelines.laser_dots.calibration", section.calibration, load_calibration)
    mount = Mount.from_config(cfg.sensors[section.camera].mount)
    optical_to_body = mount.rotation @ OPTICAL_TO_SENSOR

    def project(points_body: np.ndarray) -> np.ndarray:
        return calibration.project((points_body - mount.offset_m) @ optical_to_body)

    rig = section.beams.rig()
    heights = np.linspace(*section.height_range_m, FOV_HEIGHT_SAMPLES)
    problems = geometry.fov_problems(rig, project, calibration.width, calibration.height, heights,
                                     section.max_tilt_deg)
    if not problems:
        return []
    shown = "; ".join(problems[:FOV_PROBLEMS_SHOWN])
    more = f" (and {len(problems) - FOV_PROBLEMS_SHOWN} more)" if len(problems) > FOV_PROBLEMS_SHOWN else ""
    short_side = min(calibration.width / calibration.K[0, 0], calibration.height / calibration.K[1, 1])
    return [f"the camera {section.camera!r} loses a laser dot within height_range_m and max_tilt_deg: {shown}{more}; "
            f"for beams {rig.mean_angle_deg():.1f} deg apart the seed's eq. 41 asks a sensor size over focal length "
            f"of at least {geometry.seed_min_sensor_ratio(rig.mean_angle_deg()):.2f} (level, camera at the beams' "
            f"origin), this camera has {short_side:.2f} across its short side: a wider lens, a smaller beam angle or "
            f"a narrower envelope fixes it"]


@register_pipeline("laser_dots", LaserDotsConfig, check_files=_check_files, advise=_advise)
def _build(section: LaserDotsConfig, ctx: PipelineContext) -> LaserDotsPipeline:
    calibration, world = _load(ctx.load, section)
    mount = Mount.from_config(ctx.config.sensors[section.camera].mount)
    return LaserDotsPipeline(section, calibration, world, mount, ctx.health)
