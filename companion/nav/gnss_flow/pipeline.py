"""The ``gnss_flow`` pipeline: a fixed wing's attitude and height above ground from a single-antenna
GNSS and a forward camera, or a flow sensor's flow fields (Roberts, Walker, O'Shea 2005; issue 15).

Data flow (in the daemon's event loop, no I/O here):

- GNSS fixes (Doppler velocity, NED m/s) -> :class:`~.pseudo_attitude.DopplerAccelerationFilter`
  -> pseudo roll, pitch, yaw (the attitude of the velocity vector) at each frame's capture time;
- the flow of a pair of instants, normalised image coordinates, by either path (or both,
  :mod:`.paths`):
  the camera's, each new pair of frames (at most ``pair_rate_hz``) -> grid Lucas-Kanade flow
  (:func:`.flow.grid_flow`) -> undistorted normalised flow; or a flow sensor's (``flow``: a
  :class:`FlowField` spans its two instants and is normalised already, e.g. the seed's synthetic
  flow with its angle noise, sitl/flow_sim.py);
- that flow -> derotated by the body rates over the
  frame interval (the autopilot's gyro when ``imu_sensor`` is configured and has samples in the
  interval: its samples' interpolated mean over the interval, each taken ``gyro_delay_s`` before
  its stamp, less the bias learnt from the flow; else the rates of the pseudo Euler angles over
  ``rate_baseline_s``,
  :func:`.pseudo_attitude.body_rates_from_euler_rates`; the rate error left is estimated from the
  flow, :func:`.true_attitude.rotation_correction`: the GNSS rates' spin about the direction of
  travel, corrected in each pair, or the gyro's on every axis while the turn is at most
  ``gyro_correction_max_ratio`` times the translational flow, averaged into its bias over
  ``gyro_bias_tau_s`` (each pair's own noise is the pitch/yaw blend's to smooth); a pair turning more than
  ``max_turn_ratio`` times its translational flow gives no attitude: a rate error moves the FOE by
  itself times the depth over the speed) -> focus of expansion (each vector weighed by its
  direction's noise, the path's: a flow sensor's angle noise on the measured flow, rotation
  included, or the tracker's pixel noise) ->
  the direction of travel in the body at mid-interval -> its pitch and yaw offsets (the angle of
  attack and the drift angle) -> the true attitude: the pseudo-attitude's frame (x along the
  velocity, z along minus the normal specific force) turned by those offsets, the seed's "pseudo
  pitch plus the pitch offset normal to the roll, pseudo yaw plus the yaw offset tangential to it"
  done exactly (:mod:`.true_attitude`) -> an :class:`AttitudeEstimate` at mid-interval (the attitude cross-check,
  companion/crosscheck.py, against the autopilot's ATTITUDE; threshold and hold are the daemon's
  ``pipelines.attitude_alarm_deg`` / ``attitude_alarm_s``, one alarm for every attitude source);
- the translational flow and the GNSS speed -> depths (eqs. 9-11) -> the height above flat
  ground (eq. 12) from the points below the horizon -> a downward :class:`RangeEstimate`
  (DISTANCE_SENSOR) when it lies within ``agl_range_m``.

Two paths, two sets of estimates: each path gives its own AttitudeEstimate and RangeEstimate from
the one GNSS filter (and IMU), with its own ``source``: the flow sensor's ``gnss_flow``; the
camera's ``gnss_flow``, or ``gnss_flow.images`` when a flow sensor is configured too (so a config
with a camera only, a real vehicle's, keeps the names it had). The source names the health
component (``nav:<source>``), the cross-check (``crosscheck:<source>``), the DISTANCE_SENSOR id and
the telemetry stream (``gnss_flow`` / ``gnss_flow_images``), so a report scores the paths apart.
Their capture instants are taken in time order across both paths (the filter only moves forward).

Coordinated flight is what makes the pseudo-roll the airframe's roll. With an IMU, its
accelerometer's lateral specific force over the frame interval must stay within
``max_lateral_deg`` (:func:`.pseudo_attitude.coordination_check`); without one, the drift angle
(the FOE's yaw offset) must stay within ``max_drift_deg``, which a strong crosswind also
exceeds. A pair that fails is flagged (its path's health ``nav:<source>`` degraded with the
reason, counter ``uncoordinated``, telemetry ``coordinated: false``) and gives no attitude and no
range. Within the bound, with an IMU, the pseudo-roll blended with the gyro is first turned by
the accelerometer's lateral angle: the pseudo-roll is the roll of the specific force's plane, off
the airframe's by that angle (in SITL the roll error followed it at 0.95 deg per deg in calm air).

Time: a fix is used at its ``t_capture`` (the solution's epoch as the backend stamps it) minus
``receiver_latency_s`` (latency the backend did not remove: keep it 0 when the backend's own
``latency_s`` is set or the backend stamps the epoch, as the simulated receiver does). A frame,
or either instant of a flow field, waits until a fix at or after ``smoothing_lag_s`` past its
capture time has arrived; its pseudo-attitude is then smoothed with the fixes on both sides of it
(:meth:`.pseudo_attitude.DopplerAccelerationFilter.smoothed`), never predicted past them, and the
attitude keeps the instant's time: it describes the instant and is given the lag plus the
receiver's latency after it. With IMU samples the roll is blended with the gyro's roll rate
(``gyro_roll_tau_s``, :class:`.pseudo_attitude.GyroAidedAngle`, advanced at every fix and frame),
and each path's pitch and yaw with the gyro's pitch and yaw rates from pair to pair
(``gyro_pitch_yaw_tau_s``): the low frequencies stay the GNSS's and the flow's, the gyro's bias is
learnt, and no attitude is given until the roll's blend has run its time constant.

Frames: world LOCAL_NED, body FRD, the camera and the flow sensor each placed by its
``sensors.<name>.mount``, the optical frame of companion/calibration.py; Euler angles ZYX rad;
times on the daemon clock, s.
"""

from __future__ import annotations

import dataclasses
import heapq
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.calibration import CameraCalibration, load_calibration
from companion.frames import rotation_from_euler
from companion.health import Health, State
from companion.messages import AttitudeEstimate, Estimate, FlowField, Frame, GnssFix, ImuSample, RangeEstimate
from companion.nav.gnss_flow.config import GnssFlowConfig
from companion.nav.gnss_flow.flow import FocusOfExpansion, depths, derotate, focus_of_expansion, height_above_ground
from companion.nav.gnss_flow.paths import CameraPath, FlowPath, FlowSensorPath, GnssFlowStats, Instant, PairResult
from companion.nav.gnss_flow.pseudo_attitude import (DopplerAccelerationFilter, GyroAidedAngle, PseudoAttitude,
                                                     PseudoAttitudeLimits, body_rates_from_euler_rates,
                                                     coordination_check, euler_rates_from_body_rates, pseudo_attitude,
                                                     pseudo_attitude_refusal, pseudo_euler_rates)
from companion.nav.gnss_flow.true_attitude import (crab_roll, midway, rotation_correction, true_euler,
                                                   true_euler_covariance, turned_by_offsets, wind_to_body)
from companion.pipeline import PipelineContext
from companion.plugins import register_pipeline
from companion.timing import Timings
from drivers.mount import Mount

STREAM = "gnss_flow"
PITCH_OFFSET_TAU_S = 5.0  # the pitch offset in the gyro roll blend's Euler conversion is averaged over this, s
PITCH_OFFSET_FRESH_S = 0.5  # a pitch offset older than this (no focus of expansion since: a turn) is not measured, s
IMU_BRACKET_S = 0.25  # samples this far beyond a span bracket it for the gyro's mean (delay and IMU_HOLD_S included), s
IMU_HISTORY_S = 2.0  # IMU samples kept beyond the smoothing lag, s: a frame interval and the wait for its fix
FRAME_SLACK = 0.1  # a frame up to this fraction of 1 / pair_rate_hz early is used (capture-time jitter)
LOST_AFTER_S = 2.0  # no frame pair processed for this long (no frames, or no GNSS): health lost, s
IMU_HOLD_S = 0.1  # a blend span with no IMU sample in it takes the newest sample up to this old; older: restart, s
SAME_INSTANT_S = 1e-6  # capture times this close are one instant (the two paths' frames at 0.2 and 0.2 + 4e-17 s), s
HISTORY_MARGIN_S = 1.0  # fixes kept for the smoother beyond its lag, s: covers a frame captured before a fused fix


@dataclass
class GnssStats:
    fixes: int = 0  # GNSS fixes fed to the acceleration filter
    fixes_refused: int = 0  # no 3-D fix, no Doppler velocity, jamming, or out of time order


class GnssFlowPipeline:
    """GNSS + optic-flow attitude and height above ground; see the module docstring. Its paths
    (:attr:`paths`): the flow sensor's (source ``gnss_flow``) then the camera's (``gnss_flow``, or
    ``gnss_flow.images`` beside a flow sensor), each giving its own estimates from the one GNSS."""

    name = "gnss_flow"

    def __init__(self, cfg: GnssFlowConfig, calibration: CameraCalibration | None, camera_mount: Mount | None,
                 health: Health, flow_mount: Mount | None = None) -> None:
        """``calibration`` and ``camera_mount``: the camera's (both None without a camera);
        ``flow_mount``: the flow sensor's (None without one)."""
        self.cfg = cfg
        self.health = health
        self.flow_path = None if flow_mount is None else FlowSensorPath(STREAM, cfg, flow_mount, health)
        self.camera_path = None
        if calibration is not None and camera_mount is not None:
            source = STREAM if self.flow_path is None else f"{STREAM}.images"
            self.camera_path = CameraPath(source, cfg, calibration, camera_mount, health)
        self.paths: list[FlowPath] = [p for p in (self.flow_path, self.camera_path) if p is not None]
        if not self.paths:
            raise ValueError("gnss_flow needs a camera, a flow sensor or both")
        self.telemetry_streams = tuple(p.stream for p in self.paths)
        self.filter = DopplerAccelerationFilter(
            jerk_psd=cfg.jerk_psd, history_s=cfg.smoothing_lag_s + cfg.rate_baseline_s + HISTORY_MARGIN_S)
        self.limits = PseudoAttitudeLimits(min_ground_speed_mps=cfg.min_speed_mps)
        self.gnss_stats = GnssStats()
        self.timings = {"gnss_flow": Timings()}
        self._fixes: deque[tuple[float, GnssFix]] = deque()  # (latency-corrected epoch s, fix), in arrival order
        self._newest_epoch = -math.inf  # of any fix received, s
        # capture instants waiting for a fix at or after them: (t s, arrival number, path, payload)
        self._instants: list[tuple[float, int, FlowPath, Any]] = []
        # latency-corrected fix epochs at which the gyro roll blend is advanced between frames (s), in order
        self._blend_ticks: deque[float] = deque()
        self._arrivals = 0
        self._last_frame_s = -math.inf  # capture time of the newest camera frame kept, s
        self._imu: deque[ImuSample] = deque()
        # the gyro blends exist only with an IMU (without one they would restart at every instant)
        gyro = cfg.imu_sensor is not None
        self._gyro_roll = GyroAidedAngle(cfg.gyro_roll_tau_s) if gyro and cfg.gyro_roll_tau_s > 0 else None
        # each path's (pitch, yaw) blends with the gyro, by source
        tau = cfg.gyro_pitch_yaw_tau_s
        self._gyro_pitch_yaw = {p.source: (GyroAidedAngle(tau), GyroAidedAngle(tau))
                                for p in self.paths} if gyro and tau > 0 else {}
        self._pitch_offset: float | None = None  # the first path's pitch offsets averaged over PITCH_OFFSET_TAU_S, rad
        # the first path's newest pair: (capture time s, pitch offset rad, drift angle rad)
        self._newest_offsets: tuple[float, float, float] | None = None
        self._crab_roll = 0.0  # the roll blend's crab roll at its last instant (_crab_roll_at), rad
        # the roll blend's pitch (_carry_pitch): learning a bias of the gyro's pitch rate from the averaged offset's
        # lag and noise, it carried that into the turns (Table 1 roll std 0.28 deg instead of 0.24)
        self._carried_pitch = GyroAidedAngle(PITCH_OFFSET_TAU_S, learn_bias=False)
        # the gyro's bias (body FRD rad/s) learnt from the flow in straight flight, taken off its rates
        self.gyro_bias = np.zeros(3)

    @property
    def stats(self) -> GnssFlowStats:
        """The first path's counters (the flow sensor's, else the camera's)."""
        return self.paths[0].stats

    # -- inputs (driver callbacks) ------------------------------------------------------

    def subscriptions(self) -> dict[str, Callable[[Any], None]]:
        subs: dict[str, Callable[[Any], None]] = {self.cfg.gnss: self.on_fix}
        if self.cfg.camera is not None:
            subs[self.cfg.camera] = self.on_frame
        if self.cfg.flow is not None:
            subs[self.cfg.flow] = self.on_flow
        if self.cfg.imu_sensor is not None:
            subs[self.cfg.imu_sensor] = self.on_imu
        return subs

    def on_fix(self, fix: GnssFix) -> None:
        epoch = fix.t_capture - self.cfg.receiver_latency_s
        self._fixes.append((epoch, fix))
        if self._gyro_roll is not None and epoch > self._newest_epoch:
            self._blend_ticks.append(epoch)
        self._newest_epoch = max(self._newest_epoch, epoch)

    def on_frame(self, frame: Frame) -> None:
        assert self.camera_path is not None  # subscribed only with a camera
        self.camera_path.stats.frames += 1
        if frame.t_capture - self._last_frame_s < (1 - FRAME_SLACK) / self.cfg.pair_rate_hz:
            self.camera_path.stats.skipped_frames += 1
            return
        self._last_frame_s = frame.t_capture
        self._wait(frame.t_capture, self.camera_path, frame)

    def on_flow(self, flow: FlowField) -> None:
        assert self.flow_path is not None  # subscribed only with a flow sensor
        self.flow_path.stats.frames += 1
        if flow.t_earlier != self.flow_path.last_queued_s:  # else stamped already, as the previous field's end
            self._wait(flow.t_earlier, self.flow_path, None)
        self.flow_path.last_queued_s = flow.t_capture
        self._wait(flow.t_capture, self.flow_path, flow)

    def on_imu(self, sample: ImuSample) -> None:
        self._imu.append(sample)
        while self._imu and self._imu[0].t < sample.t - IMU_HISTORY_S - self.cfg.smoothing_lag_s:
            self._imu.popleft()

    def _wait(self, t: float, path: FlowPath, payload: Any) -> None:
        """Queue the capture instant ``t`` (s) of ``path`` until the GNSS has reached it."""
        heapq.heappush(self._instants, (t, self._arrivals, path, payload))
        self._arrivals += 1

    # -- the nav cycle --------------------------------------------------------------------

    def step(self, now: float) -> list[Estimate]:
        """Advance to daemon time ``now`` (s): the attitude and range estimates of the pairs
        whose GNSS is in (see the module docstring)."""
        started = time.perf_counter()
        out: list[Estimate] = []
        lag = self.cfg.smoothing_lag_s
        while True:
            tick = self._blend_ticks[0] if self._blend_ticks else math.inf
            if self._instants and self._instants[0][0] < tick:
                if self._instants[0][0] + lag > self._newest_epoch:
                    break
                t, _, path, payload = heapq.heappop(self._instants)
                self._feed_fixes(t + lag)
                out += self._process(path, self._stamp(t), payload)
            elif tick + lag <= self._newest_epoch:  # the gyro roll blend runs between frames too
                self._blend_ticks.popleft()
                self._feed_fixes(tick + lag)
                self._stamp(tick)
            else:
                break
        if not self._instants:  # nothing waits for the filter to stay before a fix
            self._feed_fixes(math.inf)
        elif now - self._instants[0][0] > self.filter.max_gap_s + lag:  # no GNSS for them: drop the wait
            for path in {entry[2] for entry in self._instants}:
                path.refuse(f"no GNSS fix within {self.filter.max_gap_s:g} s of the flow")
            self._instants.clear()
            for path in self.paths:
                path.reset()
        for path in self.paths:
            if path.last_pair_s is not None and now - path.last_pair_s > LOST_AFTER_S:
                self.health.report(path.component, State.LOST, f"no flow pair with GNSS for {LOST_AFTER_S:g} s")
        if out or self._instants:
            self.timings["gnss_flow"].add((time.perf_counter() - started) * 1e3)
        return out

    def _feed_fixes(self, until: float) -> None:
        """Fuse the fixes with an epoch up to ``until`` (s) into the acceleration filter."""
        keep: deque[tuple[float, GnssFix]] = deque()
        for epoch, fix in self._fixes:
            if epoch > until:
                keep.append((epoch, fix))
                continue
            v = fix.velocity_ned_mps
            usable = (fix.fix_type >= self.cfg.min_fix_type and not fix.jamming and v is not None
                      and bool(np.all(np.isfinite(v))))
            sigma = fix.speed_acc_mps if fix.speed_acc_mps is not None else self.cfg.speed_sigma_mps
            if usable and self.filter.update(epoch, np.asarray(v, dtype=float), sigma):
                self.gnss_stats.fixes += 1
            else:
                self.gnss_stats.fixes_refused += 1
        self._fixes = keep

    def _stamp(self, t: float) -> Instant:
        """The pseudo-attitude and speed at capture time ``t`` (s), from the fixes up to
        ``smoothing_lag_s`` after it (fused by the caller), the roll blended with the gyro's (the
        blend advanced to ``t``: :meth:`step` also calls this at every fix's epoch, so the blend
        has settled when the first frames come). None, with the reason, while the blend settles."""
        estimate = self.filter.smoothed(t)
        if estimate is None:
            return Instant(t, None, math.nan, "no GNSS velocity")
        refusal = pseudo_attitude_refusal(estimate.velocity_ned, estimate.acceleration_ned, self.limits)
        pseudo = None if refusal else pseudo_attitude(estimate, self.limits)
        if pseudo is not None and self._gyro_roll is not None:
            pseudo = dataclasses.replace(pseudo, roll=self._gyro_aided_roll(self._gyro_roll, pseudo))
            if self._imu and not self._gyro_roll.settled:
                pseudo, refusal = None, "gyro roll blend settling"
        return Instant(t, pseudo, float(np.linalg.norm(estimate.velocity_ned)), refusal or "")

    def _process(self, path: FlowPath, instant: Instant, payload: Any) -> list[Estimate]:
        pair = path.complete(instant, payload)
        if pair is None:
            return []
        path.last_pair_s = instant.t
        if isinstance(pair, str):
            path.refuse(pair)
            return []
        earlier, later, earlier_payload, later_payload = pair
        dt = later.t - earlier.t
        if earlier.pseudo is None or later.pseudo is None:
            path.refuse(f"no pseudo-attitude: {earlier.refusal or later.refusal}")
            return []
        if dt <= 0:
            path.refuse("frames out of time order")
            return []
        result, estimates = self._pair(path, earlier, later, path.measure(earlier_payload, later_payload))
        if path.source in self._gyro_pitch_yaw:
            result, estimates = self._gyro_aided_pitch_yaw(path, result, estimates)
        attitudes = sum(isinstance(e, AttitudeEstimate) for e in estimates)
        if attitudes:
            path.stats.attitudes += attitudes
            self.health.report(path.component, State.OK, result.status)
        path.last_result = result
        return estimates

    def _rates(self, t0: float, t1: float, mid: PseudoAttitude,
               offsets: tuple[float, float]) -> tuple[np.ndarray, str, np.ndarray | None] | None:
        """(body rates p, q, r rad/s over [t0, t1] s, their source, the mean IMU specific force
        body FRD m/s^2 over it or None without IMU samples in it), or None without either source
        (the first fixes after a gap). With IMU samples in the interval: the gyro's mean rate over
        it (:meth:`_gyro_mean`). Without: the pseudo
        Euler rates from the smoothed pseudo-attitude ``rate_baseline_s`` before ``mid`` (or at the
        oldest fix kept) to ``mid`` (differences over a frame interval are the Doppler noise's,
        amplified) turned into the pseudo frame's rates at ``mid``'s angles,
        then into the body's by the velocity ``offsets`` (pitch offset, drift rad) of the path's newest pair."""
        inside = [s for s in self._imu if t0 <= s.t <= t1]
        if inside:
            return self._gyro_mean(t0, t1), "imu", np.mean([s.accel_body for s in inside], axis=0)
        first = self.filter.first_kept_time_s
        if first is None or first >= mid.time_s:
            return None
        estimate = self.filter.smoothed(max(mid.time_s - self.cfg.rate_baseline_s, first))
        earlier = None if estimate is None else pseudo_attitude(estimate, self.limits)
        if earlier is None:
            return None
        rates = pseudo_euler_rates(earlier, mid)
        return wind_to_body(*offsets) @ body_rates_from_euler_rates(mid.roll, mid.pitch, rates), "gnss", None

    def _foe(self, path: FlowPath, points_n: np.ndarray, flows_n: np.ndarray,
             translational: np.ndarray) -> FocusOfExpansion | None:
        return focus_of_expansion(points_n, translational, noise_n=path.flow_noise_n(flows_n),
                                  threshold_sigmas=self.cfg.foe_threshold_sigmas,
                                  iterations=self.cfg.foe_iterations, min_flow=path.min_flow_n)

    def _rate_correction(self, path: FlowPath, points_n: np.ndarray, flows_n: np.ndarray, translational: np.ndarray,
                         rates: np.ndarray, dt: float, foe: FocusOfExpansion, prior_sigma_rad_s: float | None
                         ) -> tuple[np.ndarray, np.ndarray, FocusOfExpansion | None]:
        """(rates, translational flow, FOE) after ``rotation_sweeps`` corrections of ``rates`` (body FRD rad/s,
        which derotated ``flows_n`` into ``translational`` with the FOE ``foe``) from the flow
        (:func:`.true_attitude.rotation_correction`): about the direction of travel alone without a prior
        (GNSS-derived rates), on every axis with the gyro's ``prior_sigma_rad_s``; the FOE None if lost."""
        refit: FocusOfExpansion | None = foe
        for _ in range(self.cfg.rotation_sweeps):
            if refit is None:
                break
            axes = np.eye(3) if prior_sigma_rad_s is not None else (path.cam_to_body @ refit.direction_cam)[None, :]
            rates = rates + rotation_correction(points_n, flows_n, translational, refit, rates, dt, path.cam_to_body,
                                                axes, prior_sigma_rad_s)
            translational = derotate(points_n, flows_n, rates, dt, path.cam_to_body)
            refit = self._foe(path, points_n, flows_n, translational)
        return rates, translational, refit

    def _pair(self, path: FlowPath, earlier: Instant, later: Instant,
              measured: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]) -> tuple[PairResult, list[Estimate]]:
        """What the ``measured`` flow (:meth:`FlowPath.measure`) of one pair gives (see the module docstring)."""
        cfg = self.cfg
        assert earlier.pseudo is not None and later.pseudo is not None  # checked by the caller
        mid = midway(earlier.pseudo, later.pseudo)
        points_n, flows_n, points, flows = measured
        dt = later.t - earlier.t
        pseudo_euler = (mid.roll, mid.pitch, mid.yaw)
        t_mid = 0.5 * (earlier.t + later.t)  # mid's own time differs for a late frame
        base = PairResult(t_mid, pseudo_euler, points, flows)
        body_rates = self._rates(earlier.t, later.t, mid, path.offsets)
        if body_rates is None:
            reason = "no body rates: no IMU samples in the frame interval and no GNSS rate baseline"
            path.refuse(reason)
            return dataclasses.replace(base, status=reason), []
        rates, rates_source, specific_force = body_rates
        cam_to_body = path.cam_to_body
        translational = derotate(points_n, flows_n, rates, dt, cam_to_body)
        # the turn over the pair against the translational flow (normalised units): a rate error moves the FOE by
        # itself times the depth over the speed, and the flow can tell it only where the translation dominates
        turn_ratio = float(np.linalg.norm(rates)) * dt / max(float(np.median(np.linalg.norm(translational, axis=1))),
                                                              1e-12) if len(translational) else 0.0
        if turn_ratio > cfg.max_turn_ratio:
            reason = f"turning too fast for the flow: the turn {turn_ratio:.1f} times the translational flow"
            path.refuse(reason)
            return dataclasses.replace(base, status=reason, rates_source=rates_source), []
        foe = self._foe(path, points_n, flows_n, translational)
        if foe is not None and rates_source == "gnss":  # the spin about the direction of travel, for this pair
            rates, translational, foe = self._rate_correction(path, points_n, flows_n, translational, rates, dt,
                                                             foe, None)
        elif foe is not None and turn_ratio <= cfg.gyro_correction_max_ratio:
            # the gyro's error on every axis, into its bias (this pair's own noise the pitch/yaw blend's to smooth),
            # only while its turn over the pair is small beside the translational flow
            corrected, _, refit = self._rate_correction(path, points_n, flows_n, translational, rates, dt, foe,
                                                        math.radians(cfg.gyro_rate_sigma_dps))
            if refit is not None and np.all(np.isfinite(corrected)):  # a bias is kept for the flight: never NaN
                self.gyro_bias = self.gyro_bias - min(1.0, dt / cfg.gyro_bias_tau_s) * (corrected - rates)
        if foe is None:
            reason = f"no focus of expansion: {len(points_n)} flow vectors"
            path.refuse(reason)
            return dataclasses.replace(base, status=reason, rates_source=rates_source), []
        path.stats.flows += 1
        # the body at mid-interval: turned by half the interval's rotation from the earlier one's
        half_turn, _ = cv2.Rodrigues(np.asarray(rates, dtype=float) * dt / 2)  # v_body_earlier = half_turn @ v_body_mid
        cam_to_mid_body = half_turn.T @ cam_to_body
        forward = 1.0 if foe.direction_cam[2] > 0 else -1.0
        euler, offsets = true_euler(np.array(pseudo_euler), foe.point_n, forward, cam_to_mid_body,
                                    mid.along_over_normal)
        if abs(offsets[0]) > math.radians(cfg.max_pitch_offset_deg):
            reason = f"implausible focus of expansion: pitch offset {math.degrees(offsets[0]):.1f} deg"
            path.refuse(reason)
            return dataclasses.replace(base, status=reason, rates_source=rates_source, foe=foe, offsets_rad=offsets), []
        path.offsets = offsets
        if path is self.paths[0]:
            previous = offsets[0] if self._pitch_offset is None else self._pitch_offset
            self._pitch_offset = previous + min(1.0, dt / PITCH_OFFSET_TAU_S) * (offsets[0] - previous)
            self._newest_offsets = (later.t, *offsets)
        if specific_force is not None:
            coordinated, lateral = coordination_check(specific_force, math.radians(cfg.max_lateral_deg))
        else:
            lateral = offsets[1]
            coordinated = abs(lateral) <= math.radians(cfg.max_drift_deg)
        depth = depths(points_n, translational, foe.direction_cam, later.speed_mps, dt)
        result = dataclasses.replace(base, rates_source=rates_source, foe=foe, offsets_rad=offsets,
                                     coordinated=coordinated, lateral_rad=lateral, depth_m=depth)
        if not coordinated:
            path.stats.uncoordinated += 1
            reason = (f"uncoordinated manoeuvre: {'lateral specific force' if specific_force is not None else 'drift'}"
                      f" {math.degrees(lateral):.1f} deg")
            path.refuse(reason)
            return dataclasses.replace(result, status=reason), []
        t_euler = tuple(float(a) for a in euler)
        cov = true_euler_covariance(mid, foe, forward, cam_to_mid_body)
        estimates: list[Estimate] = [AttitudeEstimate(t_mid, t_euler, cov, source=path.source)]
        cam_to_level = rotation_from_euler(*t_euler) @ cam_to_mid_body  # the earlier camera's attitude
        agl = height_above_ground(points_n + translational, depth, cam_to_level, cfg.min_depression_deg)
        status = "attitude"
        low, high = cfg.agl_range_m
        if agl is not None and low <= agl <= high:
            cos_tilt = math.cos(t_euler[0]) * math.cos(t_euler[1])  # body down axis against the vertical
            distance = agl / cos_tilt
            estimates.append(RangeEstimate(later.t, distance, (cfg.agl_sigma_fraction * distance) ** 2,
                                           min_m=low, max_m=high, source=path.source))
            path.stats.ranges += 1
            status = "attitude and height above ground"
        return dataclasses.replace(result, status=status, euler_rad=t_euler, agl_m=agl), estimates

    def _gyro_aided_roll(self, blend: GyroAidedAngle, pseudo: PseudoAttitude) -> float:
        """The pseudo-roll (rad) blended with the IMU gyro's Euler roll rate since the previous
        instant (``gyro_roll_tau_s``); as it is, the blend restarting, without IMU samples covering
        that span. The pseudo-roll is first turned to the airframe's by the accelerometer's lateral
        angle (:func:`.pseudo_attitude.coordination_check`), its mean within ``lateral_window_s`` of
        the instant: as wide as the smoothed Doppler acceleration's response, so a gust's lateral
        jolt cancels between the two (over the span since the previous instant alone, the Table 1
        SITL flight's roll std was 0.166 instead of 0.154 deg), and the blend passes the rest's slow
        part only. The blend's angle is the pseudo frame's roll, which the true attitude turns by the
        crab roll (:func:`.true_attitude.crab_roll`) to the body's; the gyro's increments are the
        body's, so the crab roll's change between instants is taken off them (roll std 0.154 ->
        0.135 deg in that flight, 0.88 -> 0.64 replaying a real ArduPlane SITL flight). Beyond
        ``max_lateral_deg`` (a slip, or a push-over where the normal specific force vanishes: in SITL
        a 44 deg roll-out read 180 deg) the pseudo-roll is not the airframe's and the gyro alone
        carries the roll. The gyro's Euler rate takes the blend's roll and the body's pitch carried
        through turns (:meth:`_carry_pitch`; in a turn the yaw rate's share of the roll rate goes with
        the pitch: with one pair's offset instead of an average, its ~1 deg of flow noise put 0.5
        deg/s into the roll rate and nearly doubled the roll error, sitl/gnss_flow_flight_eval.py)."""
        last = blend.last_time_s
        if last is not None and pseudo.time_s <= last + SAME_INSTANT_S:  # the other path's instant at the same time
            return blend.update(last, pseudo.roll, 0.0)
        inside = self._imu_since(last, pseudo.time_s)
        if not inside:
            blend.reset()
            self._carried_pitch.reset()
            self._carry_pitch(pseudo, pseudo.roll, np.zeros(3), 0.0)  # restarts at the measured pitch, if there is one
            self._crab_roll = self._crab_roll_at(pseudo)
            return blend.update(pseudo.time_s, pseudo.roll, 0.0)
        window = self.cfg.lateral_window_s
        around = ([s.accel_body for s in self._imu if abs(s.t - pseudo.time_s) <= window]
                  or [s.accel_body for s in inside])
        coordinated, lateral = coordination_check(np.mean(around, axis=0), math.radians(self.cfg.max_lateral_deg))
        roll = pseudo.roll - lateral if coordinated else None
        gyro = self._gyro_mean(last, pseudo.time_s)
        dt = pseudo.time_s - last
        roll_then = blend.angle
        assert roll_then is not None  # the blend has a last time, so an angle
        rates = euler_rates_from_body_rates(roll_then, self._carry_pitch(pseudo, roll_then, gyro, dt), gyro)
        previous, self._crab_roll = self._crab_roll, self._crab_roll_at(pseudo)
        return blend.update(pseudo.time_s, roll, rates[0] * dt - (self._crab_roll - previous))

    def _crab_roll_at(self, pseudo: PseudoAttitude) -> float:
        """The crab roll (rad, :func:`.true_attitude.crab_roll`) at ``pseudo``'s instant with the first
        path's newest drift angle while its pairs measure it (within ``PITCH_OFFSET_FRESH_S``); held
        where none does (a turn: the drift turns with the wind)."""
        newest = self._newest_offsets
        if newest is None or pseudo.time_s - newest[0] > PITCH_OFFSET_FRESH_S:
            return self._crab_roll
        return crab_roll(newest[2], pseudo.along_over_normal)

    def _carry_pitch(self, pseudo: PseudoAttitude, roll: float, gyro: np.ndarray, dt: float) -> float:
        """The body pitch (rad) the roll blend converts the gyro's ``dt`` s (up to ``pseudo``'s instant,
        body rates ``gyro`` rad/s, at ``roll`` rad) with: the carried pitch at the span's start, which
        is then advanced to the instant. The carried pitch follows the pseudo-attitude turned by the
        first path's newest offsets (:func:`.true_attitude.turned_by_offsets`) while its pairs measure them
        (the newest within ``PITCH_OFFSET_FRESH_S``), smoothed over ``PITCH_OFFSET_TAU_S`` with the
        gyro's pitch rate, and the gyro alone where none does: in a turn (no focus of expansion) the
        angle of attack changes, and a stale offset put the error of the pitch times the yaw rate
        into the roll rate, up to 1.5 deg/s at 45 deg of bank in the Table 1 flight (the blend then
        carried its learnt share of it for seconds after the turn: roll errors of +1-1.5 deg).
        Before any offset: the pseudo-pitch."""
        carried = self._carried_pitch
        newest = self._newest_offsets
        measured = None
        if newest is not None and pseudo.time_s - newest[0] <= PITCH_OFFSET_FRESH_S:
            measured = float(turned_by_offsets(roll, pseudo.pitch, pseudo.yaw, newest[1], newest[2])[1])
        pitch = carried.angle
        if pitch is None:
            if measured is not None:
                carried.update(pseudo.time_s, measured, 0.0)
            return pseudo.pitch + (self._pitch_offset or 0.0)
        carried.update(pseudo.time_s, measured, euler_rates_from_body_rates(roll, pitch, gyro)[1] * dt)
        return pitch

    def _imu_since(self, last: float | None, t: float) -> list[ImuSample]:
        """The IMU samples after ``last`` up to ``t`` (s); for a span with none in it, shorter than
        the IMU's interval (the other path's instant just after), the newest up to IMU_HOLD_S old;
        none when ``last`` is None or the samples kept do not reach back to it."""
        if last is None or not self._imu or self._imu[0].t > last:
            return []
        inside = [s for s in self._imu if last < s.t <= t]
        return inside or [s for s in self._imu if t - IMU_HOLD_S < s.t <= t][-1:]

    def _gyro_mean(self, t0: float, t1: float) -> np.ndarray:
        """The gyro's mean body rate (FRD rad/s) over [t0, t1] s (:func:`mean_over` of its samples, each
        taken ``gyro_delay_s`` before its stamp: the autopilot's filter delays them) less the bias learnt
        from the flow. The caller has checked that samples reach the span."""
        delay = self.cfg.gyro_delay_s
        near = [s for s in self._imu if t0 - IMU_BRACKET_S <= s.t - delay <= t1 + IMU_BRACKET_S]
        return mean_over(np.array([s.t - delay for s in near]), np.array([s.gyro_body for s in near]),
                         t0, t1) - self.gyro_bias

    def _gyro_aided_pitch_yaw(self, path: FlowPath, result: PairResult,
                              estimates: list[Estimate]) -> tuple[PairResult, list[Estimate]]:
        """The pair's ``result`` and ``estimates`` with the attitude's pitch and yaw blended with the
        gyro's Euler rates since the path's previous pair (``gyro_pitch_yaw_tau_s``). Each pair's
        pitch and yaw are its focus of expansion's, noisy from pair to pair (std 1.6 deg in pitch
        over the Table 1 SITL flight), the gyro exact there. A pair without an attitude advances
        the blends on the gyro alone, for at most the time constant since the last attitude: in a
        45 deg banked turn (33 deg/s) the Euler pitch rate takes 0.6 deg/s of error per degree of
        roll error, 10 deg over the 15 s of a circle without a focus of expansion in SITL. After
        that, or without IMU samples over the span, the blends restart at the next pair's own. A pair
        older than the blends' newest keeps its own angles."""
        blends = self._gyro_pitch_yaw[path.source]
        last, measured_s = blends[0].last_time_s, blends[0].last_measured_s
        if last is not None and result.t_capture < last:  # a pair older than the blends' newest (a late field)
            return result, estimates
        inside = self._imu_since(last, result.t_capture)
        measured = result.euler_rad
        stale = measured_s is None or result.t_capture - measured_s > self.cfg.gyro_pitch_yaw_tau_s
        if not inside or (measured is None and stale):
            for blend in blends:
                blend.reset()
            if measured is None:
                return result, estimates
            increments = (0.0, 0.0)
        else:
            roll, pitch = (measured[0], measured[1]) if measured is not None else (
                result.pseudo_euler_rad[0], result.pseudo_euler_rad[1] + (self._pitch_offset or 0.0))
            rates = euler_rates_from_body_rates(roll, pitch, self._gyro_mean(last, result.t_capture)) * (
                result.t_capture - last)
            increments = (rates[1], rates[2])
        pitch, yaw = (blend.update(result.t_capture, None if measured is None else measured[axis + 1], increments[axis])
                      for axis, blend in enumerate(blends))
        if measured is None:
            return result, estimates
        euler = (measured[0], pitch, yaw)
        return (dataclasses.replace(result, euler_rad=euler),
                [dataclasses.replace(e, euler_rad=euler) if isinstance(e, AttitudeEstimate) else e for e in estimates])

    # -- telemetry --------------------------------------------------------------------------

    def snapshot(self) -> dict:
        """Counters for telemetry: the GNSS's and the first path's, the second path's under its source."""
        out = {**dataclasses.asdict(self.gnss_stats), **dataclasses.asdict(self.paths[0].stats)}
        return out | {p.source: dataclasses.asdict(p.stats) for p in self.paths[1:]}

    def telemetry(self, static_due: bool) -> dict[str, dict[str, Any]]:
        """Each path's newest pair's flow, FOE, depths (each shown vector's, and their summary) and
        attitudes on its stream (once per pair)."""
        return {path.stream: self._pair_telemetry(path, path.last_result) for path in self.paths
                if path.last_result is not None and path.last_result is not path.published}

    def _pair_telemetry(self, path: FlowPath, r: PairResult) -> dict[str, Any]:
        path.published = r
        step = max(1, math.ceil(len(r.points) / self.cfg.flow_vectors_shown)) if self.cfg.flow_vectors_shown else 0
        shown = slice(None, None, step) if step else slice(0, 0)
        depth = None if r.depth_m is None else r.depth_m[np.isfinite(r.depth_m)]
        return {
            "t_capture": r.t_capture, "status": r.status, "rates_source": r.rates_source,
            "gyro_bias_rad_s": self.gyro_bias if self.cfg.imu_sensor is not None else None,
            **path.telemetry_flow(r, shown), "flow_count": len(r.points),
            "flow_depth_m": None if r.depth_m is None else r.depth_m[shown],
            "foe_n": None if r.foe is None else r.foe.point_n,
            "foe_inlier_fraction": None if r.foe is None else r.foe.inlier_fraction,
            "foe_rms_deg": None if r.foe is None else r.foe.rms_angle_deg,
            "pitch_offset_rad": None if r.offsets_rad is None else r.offsets_rad[0],
            "drift_angle_rad": None if r.offsets_rad is None else r.offsets_rad[1],
            "coordinated": r.coordinated, "lateral_rad": r.lateral_rad,
            "pseudo_euler_rad": r.pseudo_euler_rad, "euler_rad": r.euler_rad,
            "depth_m": None if depth is None or not len(depth) else {
                "count": len(depth), "min": float(depth.min()), "median": float(np.median(depth)),
                "max": float(depth.max())},
            "agl_m": r.agl_m,
        }

    def operating_area(self) -> None:
        """Unbounded: GNSS works anywhere."""
        return None


def mean_over(t: np.ndarray, values: np.ndarray, t0: float, t1: float) -> np.ndarray:
    """The mean over [t0, t1] s of samples ``values`` (N, k) at the increasing times ``t`` (N,) s,
    linearly interpolated between them (held beyond the first and last): the trapezoid integral
    divided by the span; the interpolated value at ``t0`` for an empty span. A rate's mean over a
    frame pair is the rotation between its frames; the plain mean of the samples inside weighs the
    ends wrongly and misses the span's edges (at 50 Hz in the gusty Table 1 flight they are about
    as far off as each other, 13.6 mrad/s of roll rate: what matters there is the samples' filter
    delay, ``gyro_delay_s``, which takes it to 2.1)."""
    if t1 <= t0:
        return np.array([np.interp(t0, t, column) for column in np.asarray(values, dtype=float).T])
    grid = np.concatenate(([t0], t[(t > t0) & (t < t1)], [t1]))
    at = np.column_stack([np.interp(grid, t, column) for column in np.asarray(values, dtype=float).T])
    return np.trapezoid(at, grid, axis=0) / (t1 - t0)


def _load(ctx_load: Callable[..., Any], section: GnssFlowConfig) -> CameraCalibration | None:
    if section.calibration is None:
        return None
    return ctx_load("pipelines.gnss_flow.calibration", section.calibration, load_calibration)


def _check_files(cfg: Any, section: GnssFlowConfig) -> None:
    _load(cfg.load_referenced, section)


@register_pipeline("gnss_flow", GnssFlowConfig, check_files=_check_files, poses=False)
def _build(section: GnssFlowConfig, ctx: PipelineContext) -> GnssFlowPipeline:
    sensors = ctx.config.sensors
    camera_mount = None if section.camera is None else Mount.from_config(sensors[section.camera].mount)
    flow_mount = None if section.flow is None else Mount.from_config(sensors[section.flow].mount)
    return GnssFlowPipeline(section, _load(ctx.load, section), camera_mount, ctx.health, flow_mount)
