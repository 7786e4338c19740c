"""The ``ekf_slam`` pipeline: the outdoor pose while GNSS lasts, and on its loss the EKF-SLAM
return to base of Lee and Tahk (2010).

Data flow, every nav cycle, the inputs taken in capture-time order (no I/O here):

- IMU samples from the autopilot (``imu_sensor``) -> the SLAM's prediction (:class:`EkfSlam`)
  with its speed along and across the heading and its yaw rate (the gyro, as ZYX Euler rates):
  the speeds from the GNSS Doppler velocity while there is a fix, then from the autopilot's own
  velocity estimate, the motion input a vehicle still has without GNSS (the seed's commanded
  velocity and heading), each resolved along the autopilot's heading;
- landmark sightings (``landmarks``, kind landmarks, and / or the fiducial markers of the camera
  ``marker_camera``, :mod:`.markers`, levelled with the autopilot's roll and pitch at each frame's
  capture time, companion/nav/attitude_history.py) -> the SLAM's updates and new landmarks, with
  the vehicle's height measured, not assumed: the autopilot's barometric altitude on the datum
  the first GNSS heights gave it (the seed holds the altitude exact; a real one wanders, and a
  metre of height error is five sigmas of the seed's range noise), so the descent to land still
  sees the landmarks and corrects the wind's drift;
- usable GNSS fixes (``gnss``: fix type at least ``min_fix_type``, no jamming flag) -> position
  updates of the SLAM (a fix or a landmark frame captured before the SLAM's time is used at the
  pose of that moment, moved back by the current velocity). The SLAM starts at the first usable fix with the autopilot's heading
  (``start_yaw_sigma_deg``), so by the time GNSS is lost the heading and the landmarks near the
  vehicle are known in the GNSS frame from the flight so far (the seed starts at the last good fix
  with an exact heading: a real compass is not that good, and the heading error at the start
  would rotate the whole way home);
- GNSS lost (no usable fix for ``gnss_lost_after_s``) while airborne at the held altitude: the
  recovery planner (:mod:`.planner`) starts at the SLAM's pose (STEP 1) and the pipeline guides the
  vehicle (:class:`companion.pipeline.GuidanceSource`: the mission's ``return_to_base`` step, or
  the takeover of ``mission.failsafe.gnss_loss``): a point just ahead of the estimate towards the
  planner's carrot, at the held altitude, with the cruise speed as feed-forward and the nose
  along the path; the planner's new sub-maps are applied to the SLAM; near the base it lands.
  GNSS usable again for ``gnss_back_after_s`` ends the guidance of a return GNSS loss started.

Output: a :class:`PoseEstimate` every nav cycle once the SLAM runs: north and east from the SLAM,
down the measured height above (the baro on its GNSS datum; without a baro the newest fix's,
then the held altitude); roll and pitch the autopilot's, yaw the SLAM's. The covariance is the SLAM's (north, east, yaw) with the altitude's
and the autopilot attitude's stated sigmas.

Frames: LOCAL_NED at the EKF origin (GNSS fixes converted around ``origin``), body FRD; times on
the daemon clock, s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.calibration import load_calibration
from companion.frames import euler_yaw_rate, ned_from_geodetic, wrap_pi
from companion.health import Health, State
from companion.messages import Estimate, Frame, GnssFix, Guidance, ImuSample, LandmarkSightings, PoseEstimate
from companion.nav.attitude_history import AttitudeHistory
from companion.nav.ekf_slam.config import EkfSlamConfig, RecoveryPlannerConfig
from companion.nav.ekf_slam.filter import EkfSlam
from companion.nav.ekf_slam.markers import MarkerParams, MarkerSighter
from companion.nav.ekf_slam.planner import PlannerOutput, RecoveryPlanner
from companion.pipeline import PipelineContext
from companion.plugins import register_pipeline
from companion.schema import meta
from companion.timing import Timings
from companion.world import aruco_dictionary
from drivers.mount import OPTICAL_TO_SENSOR, Mount

STREAM = "ekf_slam"
HEALTH = "nav:ekf_slam"
LEAD_S = 0.2  # the guidance's position target lies this far ahead along the path (s at cruise speed)
MAX_IMU_GAP_S = 0.5  # a longer gap between IMU samples is not integrated (the SLAM waits for the next)
HOLD_FOR_IMU_S = 0.5  # a fix or a landmark frame waits at most this long for the IMU samples up to it
MAX_LATE_FIX_S = 1.0  # a fix or frame up to this far from the SLAM's time is moved to it by the velocity
DOPPLER_MAX_AGE_S = 0.6  # the GNSS Doppler velocity is the motion input this long after its fix (5 Hz + latency)
MIN_FIX_SIGMA_M = 0.1  # a receiver claiming less (or 0) is taken at this
BARO_DATUM_FIXES = 50  # the baro datum is the mean of this many fixes' heights (10 s at 5 Hz), then frozen
JUMP_RESET_M = 1.0  # a landmark frame moving the vehicle this far is sent as a position reset (see _on_sightings)
MAX_ATTITUDE_GAP_S = 0.1  # a marker frame without an IMU attitude this close to its capture time is dropped


@dataclass
class EkfSlamPipelineConfig:
    """``pipelines.ekf_slam``: GNSS while it lasts, then the EKF-SLAM return to base (Lee and Tahk)."""

    gnss: str = field(metadata=meta("Name (in `sensors`) of the GNSS receiver (kind gnss)."))
    base_ne: tuple[float, float] = field(metadata=meta(
        "Where the base is [north, east], metres in LOCAL_NED: where the return ends.", (-100000, 100000)))
    landmarks: str | None = field(default=None, metadata=meta(
        "Name (in `sensors`) of the landmark sensor (kind landmarks); null: the marker camera's only (give at "
        "least one of landmarks and marker_camera)."))
    marker_camera: str | None = field(default=None, metadata=meta(
        "Name (in `sensors`) of a camera (kind camera) whose fiducial markers are landmarks (marker id = landmark "
        "id): range and bearings from each marker's pose (ekf_slam/markers.py); null: none. The SLAM weighs them "
        "with slam.sigma_*, like the landmark sensor's."))
    marker_calibration: str | None = field(default=None, metadata=meta(
        "The marker camera's intrinsics (OpenCV or ROS YAML, relative to this file), for its frames' resolution; "
        "required with marker_camera."))
    marker_size_m: float = field(default=1.0, metadata=meta(
        "Side of a marker's black square, metres.", (0.01, 100)))
    marker_dictionary: str = field(default="DICT_4X4_250", metadata=meta(
        "OpenCV's name of the markers' dictionary (DICT_4X4_250: the simulated camera's; DICT_4X4_1000, whose "
        "first 250 are DICT_4X4_250's, for more landmarks; DICT_APRILTAG_36h11 for AprilTags)."))
    marker_id_range: tuple[int, int] = field(default=(0, 999999), metadata=meta(
        "[lowest, highest] id of the markers that are landmarks; others (e.g. a laser-dot floor's) are skipped.",
        (0, 999999)))
    marker_pixel_sigma_px: float = field(default=0.5, metadata=meta(
        "1-sigma of a marker corner per axis, pixels: the frames' stated noise (first-order; markers.py).",
        (0.01, 20)))
    imu_sensor: str = field(default="imu", metadata=meta(
        "Name (in `sensors`) of the autopilot's IMU (kind imu, backend autopilot: its samples carry the "
        "autopilot's attitude and velocity, the SLAM's motion input)."))
    speed_mps: float = field(default=5.0, metadata=meta("Cruise speed of the return, m/s (seed: 5).", (0.5, 30)))
    min_fix_type: int = field(default=3, metadata=meta(
        "A fix is usable from this MAVLink GPS_FIX_TYPE on (3 = 3-D), unless it reports jamming.", (2, 6)))
    gnss_lost_after_s: float = field(default=1.0, metadata=meta(
        "No usable fix for this long: GNSS is lost and the return to base starts.", (0.1, 60)))
    gnss_back_after_s: float = field(default=10.0, metadata=meta(
        "Usable fixes again for this long end a return GNSS loss started (a commanded one flies on).", (0.5, 600)))
    gnss_reset_after: int = field(default=5, metadata=meta(
        "This many usable fixes in a row refused by the SLAM's gate (the SLAM went wrong, or GNSS jumped) "
        "restart the SLAM at the fix, as an autopilot resets to GNSS.", (1, 1000)))
    altitude_band_m: float = field(default=5.0, metadata=meta(
        "GNSS lost within this of slam.altitude_m (the altitude the return flies at) starts the return; lost "
        "elsewhere (on the ground, climbing) it does not, metres.", (0.1, 100)))
    autopilot_velocity_sigma_mps: float = field(default=0.5, metadata=meta(
        "1-sigma of the autopilot's velocity estimate as the motion input (after GNSS loss), m/s. Its error is "
        "not white per IMU sample like the seed's commanded input: it wanders over about "
        "autopilot_velocity_tau_s, and without GNSS the autopilot's EKF takes it partly from this very "
        "estimate. Weighed as white noise of the same effect over that time (sigma * sqrt(2 tau / dt) per "
        "step), so that landmark frames keep correcting the drift instead of being refused by the gate and "
        "arriving later as jumps (seen on ArduCopter 4.0 SITL).", (0.0, 10.0)))
    autopilot_velocity_tau_s: float = field(default=1.0, metadata=meta(
        "Correlation time of the autopilot velocity's error, seconds.", (0.01, 100.0)))
    start_yaw_sigma_deg: float = field(default=5.0, metadata=meta(
        "1-sigma of the autopilot's heading the SLAM starts with (a compass), degrees.", (0.01, 90)))
    attitude_sigma_deg: float = field(default=1.0, metadata=meta(
        "1-sigma stated for the autopilot's roll and pitch in the estimate, degrees.", (0.01, 30)))
    altitude_sigma_m: float = field(default=1.0, metadata=meta(
        "1-sigma stated for the estimate's height (the baro on its GNSS datum), metres.", (0.01, 100)))
    slam: EkfSlamConfig = field(default_factory=EkfSlamConfig, metadata=meta(
        "The EKF-SLAM: held altitude, motion and sensor noise, gating, consistency fix."))
    planner: RecoveryPlannerConfig = field(default_factory=RecoveryPlannerConfig, metadata=meta(
        "The recovery path: circles around a reference landmark (or larger loops), sub-maps, search, landing."))

    def validate(self) -> tuple[str, str] | None:
        if self.landmarks is None and self.marker_camera is None:
            return "landmarks", "give a landmark sensor (landmarks), a marker camera (marker_camera) or both"
        if self.marker_camera is not None and self.marker_calibration is None:
            return "marker_calibration", "required with marker_camera: the camera's intrinsics file"
        try:
            aruco_dictionary(self.marker_dictionary)
        except ValueError as exc:
            return "marker_dictionary", str(exc)
        if self.marker_id_range[0] > self.marker_id_range[1]:
            return "marker_id_range", "give [lowest, highest] with lowest <= highest"
        if self.planner.altitude_m != self.slam.altitude_m:
            return "planner.altitude_m", f"must equal slam.altitude_m ({self.slam.altitude_m:g}): one held altitude"
        if self.planner.half_fov_deg != self.slam.half_fov_deg:
            return "planner.half_fov_deg", f"must equal slam.half_fov_deg ({self.slam.half_fov_deg:g}): one sensor"
        return None

    def sensor_inputs(self) -> dict[str, str]:
        optional = {"landmarks": "landmarks", "marker_camera": "camera"}
        given = {key: kind for key, kind in optional.items() if getattr(self, key) is not None}
        return {"gnss": "gnss", "imu_sensor": "imu", **given}

    def marker_params(self) -> MarkerParams:
        """The marker camera's :class:`MarkerParams`."""
        return MarkerParams(self.marker_size_m, aruco_dictionary(self.marker_dictionary), self.marker_id_range,
                            self.marker_pixel_sigma_px)

    def moved(self, raw: dict[str, Any], offset: tuple[float, float], move_map: Callable[[str], str]) -> dict[str, Any]:
        """This section for a local frame whose origin moved: the base shifts by ``offset`` (north,
        east m, added, as every position of the world and mission)."""
        return {**raw, "base_ne": [self.base_ne[0] + offset[0], self.base_ne[1] + offset[1]]}


def motion_input(sample: ImuSample, velocity_ned: np.ndarray | None) -> tuple[float, float, float] | None:
    """(forward, right speed m/s, yaw rate rad/s) of a vehicle moving at ``velocity_ned`` (NED
    m/s; its horizontal part resolved along and across the autopilot's heading of ``sample``) and
    turning at the ZYX yaw rate ``(q sin roll + r cos roll) / cos pitch`` of the sample's body
    rates; None without the autopilot's attitude or a velocity."""
    if sample.euler_rad is None or velocity_ned is None:
        return None
    roll, pitch, yaw = sample.euler_rad
    c, s = math.cos(yaw), math.sin(yaw)
    forward = float(velocity_ned[0] * c + velocity_ned[1] * s)
    right = float(-velocity_ned[0] * s + velocity_ned[1] * c)
    return forward, right, euler_yaw_rate(sample.gyro_body, roll, pitch)


@dataclass
class EkfSlamStats:
    fixes: int = 0
    fixes_used: int = 0
    fixes_gated: int = 0
    slam_restarts: int = 0  # restarted at a fix after gnss_reset_after gated ones
    frames: int = 0
    frames_used: int = 0  # with the vehicle's height known
    landmarks_used: int = 0
    landmarks_rejected: int = 0
    landmarks_added: int = 0
    position_resets: int = 0  # estimates sent as a reset: a landmark frame moved the vehicle JUMP_RESET_M or more
    imu_samples: int = 0
    imu_without_input: int = 0  # no autopilot attitude or velocity attached
    gnss_losses: int = 0
    submaps: int = 0
    marker_frames: int = 0  # camera frames turned into landmark sightings
    marker_frames_dropped: int = 0  # overtaken by a newer one before a nav cycle, or no IMU attitude near them
    markers_skipped: int = 0  # id outside marker_id_range or twice in a frame, or no pose


class EkfSlamPipeline:
    """GNSS, then the EKF-SLAM return to base (module docstring)."""

    name = "ekf_slam"
    telemetry_streams = (STREAM,)

    def __init__(self, cfg: EkfSlamPipelineConfig, origin: tuple[float, float, float], health: Health,
                 markers: MarkerSighter | None = None) -> None:
        """``markers``: the marker camera's sighter (required with ``cfg.marker_camera``)."""
        self.cfg = cfg
        self.markers = markers
        self.origin = origin
        self.health = health
        self.stats = EkfSlamStats()
        self.timings = {"ekf_slam": Timings()}
        self.slam: EkfSlam | None = None
        self.planner: RecoveryPlanner | None = None
        self.plan: PlannerOutput | None = None
        self.trigger = ""
        self._inbox: list[tuple[float, int, Any]] = []  # (capture time, order, message)
        self._order = 0
        self._t: float | None = None  # time the SLAM is at
        self._euler: tuple[float, float, float] | None = None
        self._down: float | None = None  # down of the newest usable fix, m
        self._gnss_ok = False  # a usable fix within gnss_lost_after_s
        self._was_at_altitude = False  # with GNSS, within altitude_band_m, at the previous cycle
        self._last_usable: float | None = None  # capture time of the newest usable fix
        self._gnss_velocity: np.ndarray | None = None  # Doppler velocity of the newest usable fix, NED m/s
        self._gnss_velocity_t = -math.inf  # its capture time
        self._velocity_ne = np.zeros(2)  # the vehicle's ground velocity by the newest motion input, m/s
        self._gated_in_a_row = 0
        self._pressure_alt: float | None = None  # newest barometric altitude from the autopilot, m up
        self._baro_datum: float | None = None  # GNSS down + pressure altitude, averaged over the first fixes
        self._datum_fixes = 0
        self._usable_since: float | None = None
        self._in_view: dict[int, np.ndarray] = {}
        self._reset_pending = False  # the next estimate is a reset (a landmark frame made the vehicle jump)
        self._attitudes = AttitudeHistory()  # the autopilot's, to level marker frames with
        health.report(HEALTH, State.LOST, "waiting for a GNSS fix")

    # -- inputs (driver callbacks) ------------------------------------------------------

    def subscriptions(self) -> dict[str, Callable[[Any], None]]:
        handlers: dict[str, Callable[[Any], None]] = {self.cfg.gnss: self._keep, self.cfg.imu_sensor: self._keep}
        if self.cfg.landmarks is not None:
            handlers[self.cfg.landmarks] = self._keep
        if self.cfg.marker_camera is not None:
            handlers[self.cfg.marker_camera] = self._keep_frame
        return handlers

    def _keep(self, message: GnssFix | LandmarkSightings | ImuSample | Frame) -> None:
        t = message.t if isinstance(message, ImuSample) else message.t_capture
        if isinstance(message, ImuSample) and message.euler_rad is not None:
            self._attitudes.add(message.t, message.euler_rad)
        self._order += 1
        self._inbox.append((t, self._order, message))

    def _keep_frame(self, frame: Frame) -> None:
        """A marker camera frame, for the nav cycle; one still waiting there is dropped (the newest
        is worth the detection's time)."""
        waiting = len(self._inbox)
        self._inbox = [m for m in self._inbox if not isinstance(m[2], Frame)]
        self.stats.marker_frames_dropped += waiting - len(self._inbox)
        self._keep(frame)

    # -- the nav cycle --------------------------------------------------------------------

    def step(self, now: float) -> list[Estimate]:
        """Take the messages received since the last cycle in capture order; the pose while the SLAM runs."""
        started = time.perf_counter()
        inbox = sorted(self._inbox, key=lambda m: (m[0], not isinstance(m[2], ImuSample), m[1]))  # IMU first on a tie
        imu_times = [t for t, _, m in inbox if isinstance(m, ImuSample)]
        horizon = max(imu_times) if imu_times else (self._t if self._t is not None else -math.inf)
        # a fix or a frame waits for the IMU samples up to its capture time (the pose it needs),
        # at most HOLD_FOR_IMU_S (an IMU that stopped does not hold the rest back for ever)
        ready = [m for m in inbox if m[0] <= horizon or now - m[0] > HOLD_FOR_IMU_S]
        self._inbox = [m for m in inbox if not (m[0] <= horizon or now - m[0] > HOLD_FOR_IMU_S)]
        for t, _, message in ready:
            if isinstance(message, GnssFix):
                self._on_fix(message)
            elif isinstance(message, LandmarkSightings):
                self._on_sightings(message)
            elif isinstance(message, Frame):
                self._on_frame(message)
            else:
                self._on_imu(message)
        self._watch_gnss(now)
        estimate = self._estimate()
        self.timings["ekf_slam"].add((time.perf_counter() - started) * 1e3)
        return [] if estimate is None else [estimate]

    def _usable(self, fix: GnssFix) -> bool:
        return fix.fix_type >= self.cfg.min_fix_type and not fix.jamming and fix.has_position

    def _on_fix(self, fix: GnssFix) -> None:
        self.stats.fixes += 1
        if not self._usable(fix):
            self._usable_since = None
            return
        self._last_usable = fix.t_capture
        self._usable_since = self._usable_since if self._usable_since is not None else fix.t_capture
        ned = ned_from_geodetic(fix.lat_deg, fix.lon_deg, fix.alt_m, self.origin)
        self._down = float(ned[2])
        if self._pressure_alt is not None and self._datum_fixes < BARO_DATUM_FIXES:
            # the baro's datum in the GNSS frame: the mean over the first fixes, then frozen (a datum
            # that followed GNSS's slowly wandering height error would move every landmark's range)
            self._datum_fixes += 1
            datum = self._down + self._pressure_alt
            self._baro_datum = datum if self._baro_datum is None else self._baro_datum + (
                datum - self._baro_datum) / self._datum_fixes
        self._gnss_velocity = fix.velocity_ned_mps
        self._gnss_velocity_t = fix.t_capture
        h = max(fix.h_acc_m if fix.h_acc_m is not None else 2.0, MIN_FIX_SIGMA_M)
        if self.slam is not None:
            assert self._t is not None  # set with the SLAM
            late = self._t - fix.t_capture  # > 0: the fix describes an instant the SLAM has moved past
            if abs(late) <= MAX_LATE_FIX_S and fix.velocity_ned_mps is not None:
                ned[:2] += fix.velocity_ned_mps[:2] * late
            if self.slam.update_position(ned[:2], np.eye(2) * h * h):
                self.stats.fixes_used += 1
                self._gated_in_a_row = 0
                return
            self.stats.fixes_gated += 1
            self._gated_in_a_row += 1
            if self._gated_in_a_row < self.cfg.gnss_reset_after or self.planner is not None:
                return  # (never while returning: fixes right after a jam may be spoofed, the map is in use)
            self.stats.slam_restarts += 1
        self._start_slam(fix.t_capture, ned, h)

    def _start_slam(self, t: float, ned: np.ndarray, h_m: float) -> None:
        """A fresh SLAM at the fix ``ned`` (m, 1-sigma ``h_m``) with the autopilot's heading."""
        if self._euler is None:
            return  # the heading to start with comes from the autopilot
        pose_cov = np.diag([h_m * h_m, h_m * h_m, math.radians(self.cfg.start_yaw_sigma_deg) ** 2])
        self._reset_pending = self.slam is not None  # a restart is a jump
        self.slam = EkfSlam(self.cfg.slam, [ned[0], ned[1], self._euler[2]], pose_cov)
        self._t = t
        self._gated_in_a_row = 0

    def _on_imu(self, sample: ImuSample) -> None:
        self.stats.imu_samples += 1
        if sample.euler_rad is not None:
            self._euler = sample.euler_rad
        if sample.pressure_alt_m is not None:
            self._pressure_alt = sample.pressure_alt_m
        fresh = self._gnss_ok and abs(sample.t - self._gnss_velocity_t) <= DOPPLER_MAX_AGE_S
        gnss = self._gnss_velocity if fresh else None
        u = motion_input(sample, gnss if gnss is not None else sample.velocity_ned)
        if u is None:
            self.stats.imu_without_input += 1
        elif self.slam is not None:  # the ground velocity it moves at now, NED m/s (for late frames)
            yaw = float(self.slam.x[2])
            self._velocity_ne = np.array([u[0] * math.cos(yaw) - u[1] * math.sin(yaw),
                                          u[0] * math.sin(yaw) + u[1] * math.cos(yaw)])
        self._predict_to(sample.t, u, autopilot_input=gnss is None)

    def _predict_to(self, t: float, u: tuple[float, float, float] | None, autopilot_input: bool = False) -> None:
        """Propagate the SLAM from its time to ``t`` (s) with the input ``u`` (forward and right
        speed, yaw rate; :func:`motion_input`); without one only the clock moves. With
        ``autopilot_input`` the speeds are the autopilot's estimate, weighed as its correlated
        error (``autopilot_velocity_sigma_mps`` over ``autopilot_velocity_tau_s``)."""
        if self.slam is None or self._t is None or t <= self._t:
            return
        dt, self._t = t - self._t, t
        if u is not None and dt <= MAX_IMU_GAP_S:
            sigma = (self.cfg.autopilot_velocity_sigma_mps * math.sqrt(2.0 * self.cfg.autopilot_velocity_tau_s / dt)
                     if autopilot_input else None)
            self.slam.predict(u[0], u[2], dt, v_right_mps=u[1], speed_sigma_mps=sigma)

    def _current_down(self) -> float | None:
        """The vehicle's NED down (m): the baro on the datum the GNSS heights gave it (smooth: a
        GNSS height is metres noisy, and the landmarks' ranges are decimetres; the datum's own
        error only shifts every landmark's height alike), else the newest fix's while GNSS
        lasts, else the held altitude while returning; None if unknown."""
        if self._baro_datum is not None and self._pressure_alt is not None:
            return self._baro_datum - self._pressure_alt
        if self._gnss_ok and self._down is not None:
            return self._down
        return self.cfg.slam.down_m if self.planner is not None else None

    def _at_altitude(self) -> bool:
        """The vehicle flies within ``altitude_band_m`` of the SLAM's held altitude."""
        down = self._current_down()
        return down is not None and abs(down - self.cfg.slam.down_m) <= self.cfg.altitude_band_m

    def _on_sightings(self, frame: LandmarkSightings) -> None:
        self.stats.frames += 1
        down = self._current_down()
        if self.slam is None or down is None:
            return
        self.stats.frames_used += 1
        self.slam.down_m = down  # the observation model's vehicle height: measured, not assumed
        observations = {int(i): np.array([r, a, e]) for i, r, a, e in
                        zip(frame.ids, frame.range_m, frame.azimuth_rad, frame.elevation_rad)}
        assert self._t is not None  # set with the SLAM
        late = self._t - frame.t_capture  # > 0: the SLAM has moved past the frame (vision latency)
        back = -self._velocity_ne * late if 0.0 < late <= MAX_LATE_FIX_S else np.zeros(2)
        before = self.slam.x[:2].copy()
        self.slam.move_vehicle(back)  # the observations are used at the pose they were taken from
        result = self.slam.update(observations, frame.sigma_of())  # weighed with the noise its sensor states
        self.slam.move_vehicle(-back)
        if np.linalg.norm(self.slam.x[:2] - before) >= JUMP_RESET_M:
            # Told as a reset (VISION_POSITION_ESTIMATE reset_counter), the autopilot's EKF moves its
            # position; filtered, it would turn part of the step into velocity, and after GNSS loss
            # that velocity is this SLAM's motion input: a loop that carried a vehicle kilometres away.
            self._reset_pending = True
            self.stats.position_resets += 1
        self.stats.landmarks_used += len(result.used)
        self.stats.landmarks_rejected += len(result.rejected)
        self.stats.landmarks_added += len(result.augmented)
        mapped = self.slam.landmarks()
        self._in_view = {i: mapped[i] for i in observations if i in mapped}
        if self.planner is not None:
            self._replan(frame.t_capture)

    def _on_frame(self, frame: Frame) -> None:
        """A marker camera frame -> its markers' sightings, levelled with the autopilot's roll and
        pitch at its capture time (interpolated between the IMU samples around it) -> :meth:`_on_sightings`."""
        assert self.markers is not None  # frames come with a marker camera
        attitude = self._attitudes.at(frame.t_capture, MAX_ATTITUDE_GAP_S)
        if attitude is None:
            self.stats.marker_frames_dropped += 1
            return
        roll, pitch, _ = attitude
        seen = self.markers.sightings(frame, roll, pitch)
        self.stats.marker_frames += 1
        self.stats.markers_skipped += seen.outside_id_range + seen.ambiguous + seen.failed
        self._on_sightings(seen.sightings)

    def _replan(self, t: float) -> None:
        assert self.slam is not None and self.planner is not None
        self.plan = self.planner.target(t, self.slam.pose, self._in_view, self.slam.landmarks())
        if self.plan.new_submap:
            self.slam.start_submap(self.plan.keep_landmark, also_keep=self.plan.also_keep)
            self.stats.submaps += 1

    def _watch_gnss(self, now: float) -> None:
        """GNSS lost at the held altitude -> start the return; back long enough -> end it. Lost elsewhere (on the ground, climbing): no return, health degraded."""
        self._gnss_ok = self._last_usable is not None and now - self._last_usable <= self.cfg.gnss_lost_after_s
        if not self._gnss_ok:
            self._usable_since = None
        if self.planner is None and not self._gnss_ok and self.slam is not None:
            if self._was_at_altitude:
                self.stats.gnss_losses += 1
                self._start_return(now, "gnss_lost")
            else:
                self.health.report(HEALTH, State.DEGRADED, "GNSS lost away from the held altitude: coasting, no return")
        elif (self.planner is not None and self.trigger == "gnss_lost" and self._usable_since is not None
              and now - self._usable_since >= self.cfg.gnss_back_after_s):
            self.planner, self.plan, self.trigger = None, None, ""
            self.health.report(HEALTH, State.OK, "GNSS back: the return to base ended")
        elif self.planner is None and self._gnss_ok and self.slam is not None:
            self.health.report(HEALTH, State.OK, "GNSS")
        self._was_at_altitude = self._gnss_ok and self._at_altitude()

    def _start_return(self, now: float, trigger: str) -> None:
        assert self.slam is not None
        self.planner = RecoveryPlanner(self.cfg.planner, self.cfg.base_ne)
        self.trigger = trigger
        self._replan(now)
        self.health.report(HEALTH, State.OK, f"returning to base on the EKF-SLAM ({trigger})")

    def _estimate(self) -> PoseEstimate | None:
        slam = self.slam
        if slam is None or self._euler is None or self._t is None:
            return None
        n, e, yaw = slam.pose
        down = self._current_down()
        if down is None:
            return None
        cov = np.zeros((6, 6))
        p = slam.pose_cov
        cov[np.ix_([0, 1], [0, 1])] = p[:2, :2]
        cov[np.ix_([0, 1], [5])] = p[:2, 2:3]
        cov[np.ix_([5], [0, 1])] = p[2:3, :2]
        cov[5, 5] = p[2, 2]
        cov[2, 2] = self.cfg.altitude_sigma_m ** 2
        cov[3, 3] = cov[4, 4] = math.radians(self.cfg.attitude_sigma_deg) ** 2
        roll, pitch, _ = self._euler
        reset, self._reset_pending = self._reset_pending, False
        return PoseEstimate(self._t, np.array([n, e, down]), (roll, pitch, float(wrap_pi(yaw))), cov, reset=reset,
                            source=self.name)

    # -- guidance (companion.pipeline.GuidanceSource) -------------------------------------

    def request_guidance(self, now: float, reason: str) -> str | None:
        """Start the return on command (a mission step); why not, if it cannot."""
        if self.planner is not None:
            return None
        if self.slam is None:
            return "the EKF-SLAM has not started (no usable GNSS fix with the autopilot's attitude yet)"
        if not self._at_altitude():
            return f"not at the held altitude of {self.cfg.slam.altitude_m:g} m (slam.altitude_m)"
        self._start_return(now, "commanded")
        return None

    def guidance(self, now: float) -> Guidance | None:
        """The planner's wish as a flight target, None while not returning."""
        if self.planner is None or self.plan is None or self.slam is None:
            return None
        plan, down = self.plan, self.cfg.slam.down_m
        n, e, yaw = self.slam.pose
        if plan.kind in ("land", "hold"):
            target = np.array([*plan.target_ne, down])
            return Guidance(now, plan.kind, target, np.zeros(3), None, self.trigger, plan.reason)
        offset = np.array(plan.carrot_ne) - np.array([n, e])
        distance = float(np.linalg.norm(offset))
        if distance < 1e-6:
            return Guidance(now, "hold", np.array([n, e, down]), np.zeros(3), None, self.trigger, plan.reason)
        along = offset / distance
        lead = min(distance, self.cfg.speed_mps * LEAD_S)
        target = np.array([n + along[0] * lead, e + along[1] * lead, down])
        velocity = np.array([along[0], along[1], 0.0]) * self.cfg.speed_mps
        return Guidance(now, "fly", target, velocity, math.atan2(along[1], along[0]), self.trigger, plan.reason)

    # -- telemetry --------------------------------------------------------------------------

    def snapshot(self) -> dict:
        """Counters for telemetry."""
        return {**self.stats.__dict__, "landmarks": 0 if self.slam is None else self.slam.n_landmarks,
                "landmarks_moved": 0 if self.slam is None else len(self.slam.moved), "in_view": sorted(self._in_view),
                "returning": self.planner is not None, "trigger": self.trigger}

    def telemetry(self, static_due: bool) -> dict[str, dict[str, Any]]:
        """The map (landmarks with their horizontal covariances), the pose and the plan."""
        slam = self.slam
        if slam is None:
            return {}
        marks = []
        for lid in slam.ids:
            mean, cov = slam.landmark(lid)
            marks.append({"id": lid, "ne": mean[:2], "cov_ne": cov[:2, :2], "in_view": lid in self._in_view})
        plan = self.plan
        return {STREAM: {
            "t_s": self._t, "pose": slam.pose, "pose_cov": slam.pose_cov, "landmarks": marks,
            "returning": self.planner is not None, "trigger": self.trigger, "base_ne": self.cfg.base_ne,
            "plan": None if plan is None else {"kind": plan.kind, "target_ne": plan.target_ne,
                                               "carrot_ne": plan.carrot_ne, "radius_m": plan.radius_m,
                                               "reason": plan.reason, "reference": plan.reference},
        }}

    def operating_area(self) -> None:
        """Unbounded outdoors (the geofence comes from mission.geofence.box_ned_m)."""
        return None


def _marker_sighter(load: Callable[..., Any], config: Any, section: EkfSlamPipelineConfig) -> MarkerSighter | None:
    """The marker camera's sighter (its calibration loaded with ``load``, its mount from ``config``), or None."""
    if section.marker_camera is None:
        return None
    calibration = load("pipelines.ekf_slam.marker_calibration", section.marker_calibration, load_calibration)
    mount = Mount.from_config(config.sensors[section.marker_camera].mount)
    return MarkerSighter(calibration, mount.rotation @ OPTICAL_TO_SENSOR, mount.offset_m, section.marker_params(),
                         section.marker_camera)


def _check_files(cfg: Any, section: EkfSlamPipelineConfig) -> None:
    _marker_sighter(cfg.load_referenced, cfg, section)


# position_sigma_m: GNSS-grade (0.7 m fixes; 0.4-0.9 m RMS in the SITL runs of the README)
@register_pipeline("ekf_slam", EkfSlamPipelineConfig, check_files=_check_files, heading=False, position_sigma_m=0.7)
def _build(section: EkfSlamPipelineConfig, ctx: PipelineContext) -> EkfSlamPipeline:
    o = ctx.config.origin
    return EkfSlamPipeline(section, (o.lat, o.lon, o.alt), ctx.health, _marker_sighter(ctx.load, ctx.config, section))
