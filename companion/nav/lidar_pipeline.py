"""The `lidar` pipeline: Wang et al.'s two-lidar localization fused with the IMU to 50 Hz.

Data flow (all in the daemon's event loop, no I/O here):

- the horizontal scanner's scans -> :class:`~companion.nav.planar.PlanarLocalizer` (x, y, yaw
  in the map = LOCAL_NED at the EKF origin) -> fusion position and yaw corrections at the
  scan's capture time;
- the vertical scanner's scans -> :class:`~companion.nav.height.HeightEstimator` (height above
  the floor) -> fusion height correction;
- the IMU sensor's samples (specific force and rates, every one, in order, with the autopilot's
  attitude: roll, pitch; yaw only as a rate) -> fusion prediction;
- every nav cycle: the fused state -> a :class:`PoseEstimate` (VISION_POSITION_ESTIMATE +
  VISION_SPEED_ESTIMATE), only while the filter is healthy. A relocalization jump or a fusion
  reset sets ``reset`` so the autopilot's ``reset_counter`` increments.

Scans are processed when the nav loop turns (the newest one of each scanner; a scan that was
overtaken before processing is counted as skipped).

Config: ``pipelines.lidar`` (:class:`LidarPipelineConfig`). Telemetry: the scan, lines, corners
and map streams (companion/nav/lidar_streams.py).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.config import MountConfig
from companion.frames import planar_increment, wrap_pi
from companion.health import Health, State
from companion.messages import Estimate, PoseEstimate, Scan
from companion.nav.corners import CornerParams
from companion.nav.edges import EdgeParams
from companion.nav.fusion import FusedState, FusionConfig, FusionFilter, without_direction
from companion.nav.fusion_io import FusedOutput, ImuFeed, to_pose_estimate
from companion.nav.heading import HeadingParams
from companion.nav.height import HeightEstimator, HeightParams
from companion.nav.lines import LineParams
from companion.nav.lidar_streams import STREAMS, ProcessedScan, map_payload, scan_payloads
from companion.nav.planar import Mount2D, PlanarFix, PlanarLocalizer, PlanarParams
from companion.pipeline import PipelineContext
from companion.plugins import register_pipeline
from companion.schema import meta
from companion.timing import Timings
from companion.world import World, load_world

LEVEL_TOLERANCE_DEG = 1.0
# The heading between two scans is predicted with the autopilot's gyro (its yaw change): a wall
# family this far (1-sigma) from that prediction is unlikely (companion/nav/heading.py).
GYRO_PREDICTION_SIGMA_DEG = 5.0
# Walls are cut at this scanner height above the floor for relocalization's wall check (an
# indoor flight height: doors and windows at it are openings the scanner sees through).
RELOCALIZATION_SCAN_HEIGHT_M = 1.0
PLANAR_HEALTH = {"tracking": State.OK, "degraded": State.DEGRADED, "lost": State.LOST}


@dataclass
class LidarPipelineStats:
    horizontal_scans: int = 0
    vertical_scans: int = 0
    skipped_scans: int = 0  # overtaken by a newer scan before the nav loop got to them
    planar_fixes: int = 0  # measured fixes given to the fusion
    height_fixes: int = 0
    relocalizations: int = 0
    first_fix_t: float | None = None
    last_fix_t: float | None = None

    def fix_rate_hz(self) -> float | None:
        """Measured planar fixes per second of daemon time."""
        if self.first_fix_t is None or self.last_fix_t is None or self.last_fix_t <= self.first_fix_t:
            return None
        return (self.planar_fixes - 1) / (self.last_fix_t - self.first_fix_t)


@dataclass
class LidarPipelineConfig:
    """``pipelines.lidar``: the two-lidar localization of Wang et al. (horizontal: x, y, yaw;
    vertical: height), fused with the IMU."""

    horizontal_sensor: str = field(metadata=meta("Name (in `sensors`) of the horizontal scanner."))
    vertical_sensor: str = field(metadata=meta("Name (in `sensors`) of the vertical scanner: height above the floor."))
    imu_sensor: str = field(default="imu", metadata=meta(
        "Name (in `sensors`) of the IMU the fusion predicts with (e.g. kind imu, backend autopilot)."))
    map: str = field(default="worlds/arena.yaml", metadata=meta(
        "Map (world YAML: walls, known corners, wall_angle_deg), relative to this file."))
    initial_pose: tuple[float, float, float] | None = field(default=None, metadata=meta(
        "Start pose [north m, east m, yaw deg] in the map; null = relocalize globally from the first scans."))
    correspondence_gate_m: float = field(default=0.5, metadata=meta(
        "Nearest-neighbour gate between an observed and a map corner.", (0.05, 5)))
    relocalization_confirm_scans: int = field(default=3, metadata=meta(
        "Scans that must find a relocalization jump (each near the previous one moved as the fused IMU says, turned "
        "as the gyro says; scans too poor to test it carry it, one finding another pose starts over) before it "
        "becomes the pose; until then the lidar pose is lost.", (1, 40)))
    # The noise the vehicle's sensors and building add beyond what each fit sees (the map's own, its
    # survey error, is in the map unless survey_error_m is set). The defaults suit a real multirotor
    # with a Hokuyo in a real building (README, "The noise floors as settings").
    survey_error_m: float | None = field(default=None, metadata=meta(
        "1-sigma survey error of the map's walls and corners, m, in place of the map file's `survey_error_m`; null: "
        "the map file's. A simulated world that is its own map is exact (config/sitl-declared.yaml declares 0).",
        (0.0, 1.0)))
    accel_noise_density: float = field(default=FusionConfig.accel_noise_density, metadata=meta(
        "White acceleration noise of the fusion's IMU prediction, m/s^2/sqrt(Hz): the IMU's own plus the autopilot's "
        "tilt error seen through gravity, vibration, impacts (the part ArduPilot's EK3_ACC_P_NSE plays).",
        (1e-5, 1.0)))
    yaw_rate_noise_density: float = field(default=FusionConfig.yaw_rate_noise_density, metadata=meta(
        "White noise of the fusion's yaw prediction from the gyro, rad/sqrt(s): the gyro's noise and the bias its "
        "calibration leaves, over the interval between heading fixes.", (1e-6, 0.1)))
    fix_time_sd_s: float = field(default=FusionConfig.fix_time_sd_s, metadata=meta(
        "1-sigma error of a scan's capture time on the autopilot IMU's time line, s (the scanner's and the "
        "autopilot's clocks each mapped onto the daemon's, the autopilot's accelerometer filter): each fix's "
        "variance grows by (velocity x this)^2 along the velocity, so fast flight trusts a fix less (ArduCopter "
        "SITL's TCP link measured 11-12 ms at the median); 0: taken as exact.",
        (0.0, 0.2)))
    line_model_error_m: float = field(default=LineParams.model_floor_m, metadata=meta(
        "1-sigma error of every fitted line beyond what its residuals show (wall roughness, a range bias that "
        "depends on the surface), m; both scanners.", (0.0, 0.1)))
    corner_error_per_m: float = field(default=CornerParams.floor_per_m, metadata=meta(
        "1-sigma error of every corner per metre of range (beam width, rounded corners), m/m.", (0.0, 0.05)))
    heading_error_deg: float = field(default=math.degrees(math.sqrt(HeadingParams.variance_floor_rad2)), metadata=meta(
        "1-sigma floor of the heading the lines measure (the scanner's alignment, walls a little off the map's wall "
        "angle), degrees; the map's own `wall_direction_error_deg` is added to each fix's heading.", (0.0, 5.0)))
    height_model_error_m: float = field(default=math.sqrt(HeightParams.variance_floor_m2), metadata=meta(
        "1-sigma error of every height fix beyond its floor line's fit (an uneven floor), m; 0 only for an exactly "
        "flat floor (a simulated one).", (0.0, 0.5)))
    attitude_error_deg: float = field(default=HeightParams.attitude_sd_deg, metadata=meta(
        "1-sigma error of the autopilot's roll and pitch, degrees: the height fix levels each floor line with them "
        "where its own fitted direction is less certain (a far floor line's at grazing angles).", (0.0, 10.0)))
    mixed_pixels: bool = field(default=EdgeParams.mixed_pixels, metadata=meta(
        "Whether the horizontal scanner may return a range between two surfaces at a depth edge (every real "
        "one does): a wall's end seen at a slant is then known only to within the line extraction's tolerance "
        "over the tangent of the view's angle (companion/nav/edges.py); false only for a scanner without them "
        "(a simulated one)."))
    floor_tilt_error_deg: float = field(default=HeightParams.floor_tilt_sd_deg, metadata=meta(
        "1-sigma tilt of the floor under a floor line against the level, degrees (an uneven floor: a 4 mm rise "
        "over 1 m, what DIN 18202 allows a finished floor, is 0.23 deg): how far a floor line's own direction "
        "may lead its height off when carried to under the vehicle; 0 only for an exactly flat floor (a simulated "
        "one).", (0.0, 10.0)))

    def sensor_inputs(self) -> dict[str, str]:
        return {"horizontal_sensor": "lidar", "vertical_sensor": "lidar", "imu_sensor": "imu"}

    def moved(self, raw: dict[str, Any], offset: tuple[float, float], move_map: Callable[[str], str]) -> dict[str, Any]:
        """This section (``raw``, as written) for a local frame whose origin moved: positions shift by
        ``offset`` (north, east m); ``move_map(path)`` gives the path of the map in that frame."""
        out = {**raw, "map": move_map(self.map)}
        if self.initial_pose is not None:
            x, y, yaw = self.initial_pose
            out["initial_pose"] = [x + offset[0], y + offset[1], yaw]
        return out


def wall_ends_floor(fix: PlanarFix, kept: tuple[np.ndarray, float] | None) -> tuple[np.ndarray, float] | None:
    """The direction (unit north, east) that only wall ends measure and the least variance (m^2)
    the estimate may claim along it (LidarPipeline._with_shared_errors), after the measured ``fix``
    (``kept``: that floor before it): that fix's own if wall ends alone measured a direction; kept
    if the fix measured that direction no better (a corridor's walls without an end in view, one
    corner without a cross-check): the estimate there still rests on the earlier ends, and dropping
    the floor for such a scan let it claim 1.3 cm along the realistic corridor (seed 3) at 5-6 cm
    error; none once a fix measured it better (corners)."""
    if fix.ends_only is not None:
        u = np.array(fix.ends_only)
        return u, float(u @ fix.covariance[:2, :2] @ u)
    if kept is not None and float(kept[0] @ fix.covariance[:2, :2] @ kept[0]) >= kept[1]:
        return kept
    return None


def planar_params(cfg: LidarPipelineConfig, survey_error_m: float = CornerParams.floor_m,
                  wall_direction_error_deg: float = 0.0) -> PlanarParams:
    """The localizer's thresholds and noise floors from the config and the map's survey error (m,
    1-sigma: the floor of every corner's and wall's covariance) and wall direction error (deg,
    1-sigma: added to every heading's variance); the rest keep the defaults of companion/nav."""
    defaults = PlanarParams()
    lines = dataclasses.replace(defaults.lines, model_floor_m=cfg.line_model_error_m)
    return PlanarParams(gate_m=cfg.correspondence_gate_m, reloc_confirm_frames=cfg.relocalization_confirm_scans,
                        corners=CornerParams(floor_m=survey_error_m, floor_per_m=cfg.corner_error_per_m),
                        map_error_m=survey_error_m, lines=lines,
                        edges=dataclasses.replace(defaults.edges, mixed_pixels=cfg.mixed_pixels),
                        heading=HeadingParams(prediction_sigma_deg=GYRO_PREDICTION_SIGMA_DEG,
                                              variance_floor_rad2=math.radians(cfg.heading_error_deg) ** 2),
                        map_heading_error_rad=math.radians(wall_direction_error_deg))


def height_params(cfg: LidarPipelineConfig) -> HeightParams:
    """The vertical scanner's height fix with the config's noise floors."""
    lines = dataclasses.replace(HeightParams().lines, model_floor_m=cfg.line_model_error_m)
    return HeightParams(lines=lines, variance_floor_m2=cfg.height_model_error_m ** 2,
                        attitude_sd_deg=cfg.attitude_error_deg, floor_tilt_sd_deg=cfg.floor_tilt_error_deg)


def planar_mount(mount: MountConfig) -> Mount2D:
    """The horizontal scanner's 2-D mount; it must be mounted level (roll, pitch 0)."""
    roll, pitch, yaw = mount.rpy_deg
    if abs(roll) > LEVEL_TOLERANCE_DEG or abs(pitch) > LEVEL_TOLERANCE_DEG:
        raise ValueError(f"the horizontal scanner must be mounted level (roll, pitch 0), got rpy_deg {list(mount.rpy_deg)}")
    x, y, z = mount.position_m
    return Mount2D(x_m=x, y_m=y, yaw_rad=math.radians(yaw), z_m=z)


def planar_localizer(params: PlanarParams, world_map: World, mount: Mount2D,
                     initial_pose: tuple[float, float, float] | None) -> PlanarLocalizer:
    """The horizontal scanner's localizer on ``world_map`` (its corners, walls at the flight height,
    ceiling and wall directions); ``initial_pose``: x, y (m), yaw (rad) in the map, None to
    relocalize globally."""
    return PlanarLocalizer(world_map.corner_array(), world_map.wall_angle_deg, mount,
                           walls=world_map.segments_at(RELOCALIZATION_SCAN_HEIGHT_M), params=params,
                           initial_pose=initial_pose,
                           ceiling_m=max((w.height_m for w in world_map.walls), default=None),
                           wall_offset_deg=world_map.wall_offset_deg)


class LidarPipeline:
    """Two-lidar localization + fusion; see the module docstring."""

    name = "lidar"
    telemetry_streams = STREAMS

    def __init__(self, cfg: LidarPipelineConfig, world_map: World, horizontal: MountConfig,
                 vertical: MountConfig, health: Health) -> None:
        self.cfg = cfg
        self.world_map = world_map
        self.survey_error_m = world_map.survey_error_m if cfg.survey_error_m is None else cfg.survey_error_m
        self.health = health
        initial = None
        if cfg.initial_pose is not None:
            x, y, yaw_deg = cfg.initial_pose
            initial = (x, y, math.radians(yaw_deg))
        self.localizer = planar_localizer(planar_params(cfg, self.survey_error_m, world_map.wall_direction_error_deg),
                                          world_map,
                                          planar_mount(horizontal), initial)
        self.height = HeightEstimator(tuple(vertical.position_m), tuple(math.radians(a) for a in vertical.rpy_deg),
                                      height_params(cfg))
        self.fusion = FusionFilter(FusionConfig(accel_noise_density=cfg.accel_noise_density,
                                                yaw_rate_noise_density=cfg.yaw_rate_noise_density,
                                                fix_time_sd_s=cfg.fix_time_sd_s))
        self.output = FusedOutput(self.fusion, health, "nav:fusion")
        self.stats = LidarPipelineStats()
        self.timings = {"lidar": Timings(), "fusion": Timings()}
        self._horizontal: Scan | None = None
        self._vertical: Scan | None = None
        self.imu = ImuFeed()
        self._published: ProcessedScan | None = None  # the last scan telemetry() returned
        self._scan_yaw: float | None = None  # autopilot yaw at the previous horizontal scan
        self._scan_state: tuple[float, float, float] | None = None  # fused x, y (m), yaw (rad) there, if healthy
        self._coasting = False  # the previous horizontal fix matched no corner: its position is stale
        self._map_features = 1  # corners (or walls) the newest measured fix matched
        # (unit direction, variance m^2) that the newest measured fix measured by wall ends alone
        self._ends_only: tuple[np.ndarray, float] | None = None
        self.last_horizontal: ProcessedScan | None = None  # read-only, for telemetry
        health.report("nav:lidar", State.LOST, "waiting for scans")

    # -- inputs (driver callbacks) ------------------------------------------------------

    def subscriptions(self) -> dict[str, Callable[[Any], None]]:
        return {self.cfg.horizontal_sensor: self.on_horizontal_scan, self.cfg.vertical_sensor: self.on_vertical_scan,
                self.cfg.imu_sensor: self.imu.add}

    def on_horizontal_scan(self, scan: Scan) -> None:
        self.stats.horizontal_scans += 1
        self.stats.skipped_scans += self._horizontal is not None
        self._horizontal = scan

    def on_vertical_scan(self, scan: Scan) -> None:
        self.stats.vertical_scans += 1
        self.stats.skipped_scans += self._vertical is not None
        self._vertical = scan

    # -- the nav cycle --------------------------------------------------------------------

    def step(self, now: float) -> list[Estimate]:
        """Advance to daemon time ``now`` (s); the fused estimate, or none while not healthy."""
        started = time.perf_counter()
        self.imu.predict(self.fusion)
        predicted = time.perf_counter()
        scan_ms = 0.0
        if self._horizontal is not None:
            scan_ms += self._process_horizontal(self._horizontal)
            self._horizontal = None
        if self._vertical is not None:
            scan_ms += self._process_vertical(self._vertical)
            self._vertical = None
        if scan_ms:
            self.timings["lidar"].add(scan_ms)
        resumed = time.perf_counter()
        estimate = self._output(now)
        self.timings["fusion"].add((predicted - started + time.perf_counter() - resumed) * 1e3)
        return [] if estimate is None else [estimate]

    def _process_horizontal(self, scan: Scan) -> float:
        roll, pitch, yaw = self.imu.euler_at(scan.t_capture + scan.sweep_s / 2.0)  # levelled at mid-sweep
        yaw_delta = 0.0 if self._scan_yaw is None else wrap_pi(yaw - self._scan_yaw)
        self._scan_yaw = yaw
        state = self.fusion.state(scan.t_capture)
        height = -float(state.position_ned[2]) if state.healthy else None  # floor hits dropped with it
        # While no corner is matched (a corridor, a blank wall) the localizer's position is stale: the
        # fused one (IMU-propagated) predicts the next scan instead, along the unmeasured direction too.
        held = self.localizer.pose
        prior = None
        if self._coasting and state.healthy and held is not None:
            prior = (float(state.position_ned[0]), float(state.position_ned[1]), held[2])
        moved = self._moved_since_last_scan(state)
        started = time.perf_counter()
        fix = self.localizer.update(scan, prior, roll=roll, pitch=pitch, yaw_delta=yaw_delta, moved_m=moved,
                                    height_m=height)
        elapsed = (time.perf_counter() - started) * 1e3
        self._coasting = fix is not None and fix.matched == 0
        assert self.localizer.last_lines is not None and self.localizer.last_corners is not None  # set by update()
        self.last_horizontal = ProcessedScan(scan, roll, pitch, fix, self.localizer.last_lines,
                                             self.localizer.last_corners)
        if fix is None:
            self.health.report("nav:lidar", State.LOST, self.localizer.last_reason or "no pose: relocalizing")
            return elapsed
        self.health.report("nav:lidar", PLANAR_HEALTH[fix.state], fix.reason or f"{fix.matched} corners matched")
        if fix.relocalized:
            self.stats.relocalizations += 1
            self.fusion.reset(np.array([fix.x, fix.y, state.position_ned[2]]), fix.yaw, scan.t_capture)
        elif fix.measured:
            position_cov = fix.covariance[:2, :2]
            if fix.unmeasured is not None:  # a corridor: only the cross-track position is a measurement
                position_cov = without_direction(position_cov, fix.unmeasured)
            self.fusion.correct_pose(scan.t_capture, np.array([fix.x, fix.y]), position_cov, fix.yaw,
                                     float(fix.covariance[2, 2]))
        if fix.measured:
            self._map_features = max(fix.matched, fix.walls_matched, 1)
            self._ends_only = wall_ends_floor(fix, self._ends_only)
            self.stats.planar_fixes += 1
            self.stats.first_fix_t = self.stats.first_fix_t if self.stats.first_fix_t is not None else scan.t_capture
            self.stats.last_fix_t = scan.t_capture
        return elapsed

    def _moved_since_last_scan(self, state: FusedState) -> tuple[float, float]:
        """The fused displacement since the previous horizontal scan in the body frame then
        (forward, right, m); zero unless the fusion was healthy at both scans."""
        before = self._scan_state
        self._scan_state = (float(state.position_ned[0]), float(state.position_ned[1]), state.yaw) if state.healthy else None
        if before is None or self._scan_state is None:
            return (0.0, 0.0)
        forward, right, _ = planar_increment(before, self._scan_state)
        return (forward, right)

    def _process_vertical(self, scan: Scan) -> float:
        # Levelled with the attitude when the scanner looked straight down: the floor's beams.
        roll, pitch, _ = self.imu.euler_at(scan.t_capture + scan.sweep_s * self.height.floor_beam_fraction(scan))
        # The IMU-carried height, also once the fusion reports it lost: a floor hidden for a second (a
        # table top alone in view) is when a table top must still not become the floor, or the fusion
        # re-seeds its height to it. Not initialised, its variance (1e6 m^2) refuses nothing by itself;
        # a table remembered where the vehicle is still may (companion/nav/height.py). The localizer's
        # pose (known without a height) says where the surfaces seen lie.
        state = self.fusion.state(scan.t_capture)
        expected = (-float(state.position_ned[2]), math.sqrt(float(state.position_covariance[2, 2])))
        started = time.perf_counter()
        fix = self.height.update(scan, roll, pitch, expected=expected, pose=self.localizer.pose)
        elapsed = (time.perf_counter() - started) * 1e3
        if fix.state == "lost":
            self.health.report("nav:height", State.LOST, fix.reason)
            return elapsed
        self.health.report("nav:height", State.OK if fix.state == "ok" else State.DEGRADED, fix.reason or "floor found")
        self.fusion.correct_height(scan.t_capture, fix.height_m, fix.variance)
        self.stats.height_fixes += 1
        return elapsed

    def _output(self, now: float) -> PoseEstimate | None:
        fused = self.output.at(now)
        if fused is None:
            return None
        state, reset = fused
        roll, pitch, _ = self.imu.euler
        return to_pose_estimate(self._with_shared_errors(state), roll, pitch, reset=reset, source=self.name)

    def _with_shared_errors(self, state: FusedState) -> FusedState:
        """``state`` with the errors successive fixes share added to its horizontal position
        covariance; they are biases common to those fixes, not noise that averaging removes, so
        the filter's covariance (of the position in the map) shrinks below them while the error
        against the building does not:

        - the map's: its survey error (m, 1-sigma) over the corners or walls the newest fix matched,
          and its wall direction error (deg, 1-sigma), which the yaw variance does not go below (the
          heading is measured against the map's walls, the same ones from scan to scan);
        - the wall ends': where the newest fix measured a direction by wall ends alone (a
          corridor's axis), the variance along it is at least that fix's (where between two beams
          a wall ends stays the same while the vehicle moves less than a beam spacing: hovering
          near a recess, the fused estimate otherwise claimed 1.5 cm along the corridor with
          errors up to 5 cm, from one fix's 3 cm).
        """
        survey = self.survey_error_m
        cov = state.position_covariance.copy()
        cov[0, 0] += survey * survey / self._map_features
        cov[1, 1] += survey * survey / self._map_features
        if self._ends_only is not None:
            u, least = self._ends_only
            short = least - float(u @ cov[:2, :2] @ u)
            if short > 0.0:
                cov[:2, :2] += short * np.outer(u, u)
        yaw_variance = max(state.yaw_variance, math.radians(self.world_map.wall_direction_error_deg) ** 2)
        return dataclasses.replace(state, position_covariance=cov, yaw_variance=yaw_variance)

    def snapshot(self) -> dict:
        """Telemetry: counters, the fix rate, the relocalization candidate waiting for confirmation
        and the newest relocalization's hypotheses with their scores and outcome (empty while tracking;
        positions m LOCAL_NED north, east; yaw rad)."""
        loc = self.localizer
        c = loc.candidate
        candidate = None if c is None else {
            "position_ned_m": (c.x, c.y), "yaw_rad": c.yaw, "matched": c.matched, "walls": c.walls, "local": c.local,
            "frames": c.frames, "frames_needed": loc.params.reloc_confirm_frames}
        hypotheses = [{"position_ned_m": [h.x, h.y], "yaw_rad": h.yaw, "source": h.source, "corners": h.corners,
                       "wall_fraction": h.wall_fraction, "local": h.local} for h in loc.hypotheses]
        return {**{k: v for k, v in vars(self.stats).items()}, "fix_rate_hz": self.stats.fix_rate_hz(),
                "fusion": {"gated": dict(self.fusion.stats.fixes_gated), "stale": self.fusion.stats.fixes_stale},
                "relocalization_candidate": candidate, "relocalization_hypotheses": hypotheses,
                "relocalization_outcome": loc.reloc_outcome}

    def telemetry(self, static_due: bool) -> dict[str, dict[str, Any]]:
        """The newest processed scan's scan, lines and corners (once per scan); the map when due."""
        out: dict[str, dict[str, Any]] = {}
        record = self.last_horizontal
        if record is not None and record is not self._published:
            self._published = record
            out.update(scan_payloads(record, self.localizer))
        if static_due:
            out["map"] = map_payload(self.localizer)
        return out

    def operating_area(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The map's bounds, m (north, east)."""
        b = self.world_map.bounds
        return (float(b.min[0]), float(b.min[1])), (float(b.max[0]), float(b.max[1]))


def _check_map(cfg: Any, section: LidarPipelineConfig) -> None:
    cfg.load_referenced("pipelines.lidar.map", section.map, load_world)


@register_pipeline("lidar", LidarPipelineConfig, check_files=_check_map)
def _build(section: LidarPipelineConfig, ctx: PipelineContext) -> LidarPipeline:
    sensors = ctx.config.sensors
    world_map = ctx.load("pipelines.lidar.map", section.map, load_world)
    return LidarPipeline(section, world_map, sensors[section.horizontal_sensor].mount,
                         sensors[section.vertical_sensor].mount, ctx.health)
