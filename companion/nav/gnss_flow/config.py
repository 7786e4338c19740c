"""``pipelines.gnss_flow``'s settings (the pipeline: companion/nav/gnss_flow/pipeline.py)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from companion.messages import GNSS_3D
from companion.schema import meta


@dataclass
class GnssFlowConfig:
    """``pipelines.gnss_flow``: a fixed wing's attitude and height above ground from GNSS and optic flow."""

    gnss: str = field(metadata=meta("Name (in `sensors`) of the GNSS receiver (kind gnss, with Doppler velocity)."))
    camera: str | None = field(default=None, metadata=meta(
        "Name (in `sensors`) of the forward-looking camera (kind camera): the image path, grid Lucas-Kanade flow; "
        "null: none (give `flow`). Its estimates' source is `gnss_flow`, or `gnss_flow.images` when `flow` is "
        "given too."))
    calibration: str | None = field(default=None, metadata=meta(
        "The camera's intrinsics (OpenCV or ROS YAML, relative to this file), for the frames' resolution; "
        "needed with `camera`."))
    flow: str | None = field(default=None, metadata=meta(
        "Name (in `sensors`) of a flow sensor (kind flow: flow fields in normalised image coordinates, e.g. the "
        "seed's synthetic flow, `backend: sim`): the flow path, from the derotation on (no tracking, no "
        "calibration); its estimates' source is `gnss_flow`. null: none (give `camera`)."))
    imu_sensor: str | None = field(default=None, metadata=meta(
        "Name (in `sensors`) of the autopilot's IMU (kind imu), optional: its gyro derotates the flow and its "
        "accelerometer checks the coordination; null: GNSS-derived body rates and the drift-angle check."))
    pair_rate_hz: float = field(default=10.0, metadata=meta(
        "Camera frames are used at most this often (the others are skipped; a flow sensor's fields all are): one "
        "flow per interval, each costing a grid_flow (`companion bench`) in the nav loop; a longer interval gives "
        "the far ground more flow.",
        (0.5, 100)))
    grid: tuple[int, int] = field(default=(45, 45), metadata=meta(
        "Flow grid, [columns, rows] of points spread over the image (seed: 45 x 45).", (2, 200)))
    lk_window_px: int = field(default=16, metadata=meta(
        "Lucas-Kanade window side, pixels: a larger one biases the ground's flow, whose expansion varies across "
        "the window (21 px put the angle of attack 0.6 deg low in tests/test_gnss_flow_pipeline.py, 16 px within "
        "0.1 deg); OpenCV is fastest at multiples of 8 (flow.grid_flow).", (4, 101)))
    lk_levels: int = field(default=3, metadata=meta("Lucas-Kanade pyramid levels above the image.", (0, 8)))
    fb_max_px: float = field(default=0.5, metadata=meta(
        "A grid point whose forward-backward tracking error exceeds this is dropped, pixels.", (0.01, 10)))
    foe_min_flow_px: float = field(default=1.0, metadata=meta(
        "Translational flow vectors shorter than this are not used for the focus of expansion (the far ground's: "
        "their directions are tracking noise), pixels.", (0, 50)))
    foe_min_flow_n: float = field(default=2e-4, metadata=meta(
        "The flow path's `foe_min_flow_px`: shorter translational flow vectors of a flow sensor are not used for "
        "the focus of expansion, normalised image units (about radians near the axis).", (0, 1)))
    foe_threshold_sigmas: float = field(default=3.5, metadata=meta(
        "A translational flow vector within this many of its direction's noise sigmas of its line from the focus "
        "of expansion is a RANSAC inlier (at most 45 deg; the noise: `flow_angle_sigma_deg`, `lk_sigma_px`).",
        (0.5, 20)))
    flow_angle_sigma_deg: float = field(default=1.44, metadata=meta(
        "1-sigma direction noise of a flow sensor's vectors, degrees: on the measured flow, rotation included, so "
        "in a turn it is larger on the translational flow that is left (the seed's uniform +/-2.5 deg: 1.44).",
        (0.01, 45)))
    lk_sigma_px: float = field(default=0.1, metadata=meta(
        "1-sigma error of a Lucas-Kanade flow vector (each axis), pixels.", (0.001, 10)))
    foe_iterations: int = field(default=50, metadata=meta(
        "RANSAC draws of two flow lines for the focus of expansion (each votes over every flow vector; the least "
        "squares fit on the winner's inliers follows): 50 find an inlier pair at once with half the flow outliers.",
        (1, 1000)))
    receiver_latency_s: float = field(default=0.0, metadata=meta(
        "GNSS receiver latency the backend did not remove: a fix is used at t_capture minus this, s (0 when the "
        "backend's latency_s is set or it stamps the solution's epoch, as `backend: sim` does).", (0, 2)))
    speed_sigma_mps: float = field(default=0.1, metadata=meta(
        "1-sigma of a Doppler velocity component when the receiver does not report its speed accuracy, m/s.",
        (0.001, 10)))
    rate_baseline_s: float = field(default=1.0, metadata=meta(
        "Without IMU samples: the pseudo Euler rates are differenced over this span of fixes, s. The flow's focus "
        "of expansion is very sensitive to a roll-rate error (1 deg/s turns the far ground's flow lines by tens of "
        "degrees), and the pseudo-roll's noise differenced over a frame interval gives several deg/s; longer is "
        "smoother and lags a roll-in by half of it.", (0.05, 5)))
    rotation_sweeps: int = field(default=2, metadata=meta(
        "Times the rate error the derotation missed is re-estimated from the flow and the focus of expansion "
        "refitted (true_attitude.rotation_correction): with GNSS-derived rates the turn rate about the direction "
        "of travel (the pseudo roll rate's error), with the gyro its error on every axis (its bias: 1 mrad/s of "
        "yaw-rate bias moves the focus of expansion about a degree at 100 m and 17 m/s), 0 = never.", (0, 10)))
    gyro_delay_s: float = field(default=0.011, metadata=meta(
        "How late the autopilot's IMU samples show the gyro's rate (its low-pass filter's delay), s: a sample is "
        "used this long before its stamp. ArduPilot's two-pole INS_GYRO_FILTER at 20 Hz: about 0.011; a first-order "
        "low pass at f Hz: 1 / (2 pi f).", (0, 0.1)))
    gyro_rate_sigma_dps: float = field(default=0.2, metadata=meta(
        "1-sigma of the gyro's rate error over a pair (bias and noise), the prior of the rate correction from the "
        "flow: what the flow cannot tell stays the gyro's, deg/s.", (0.001, 10)))
    max_turn_ratio: float = field(default=3.0, metadata=meta(
        "A pair whose turn (the body rates times its interval) is more than this many times its median "
        "translational flow (normalised units) gives no attitude: a rate error of the gyro (its scale, its "
        "filter's lag) moves the focus of expansion by itself times the depth over the speed, and the flow cannot "
        "tell it apart (at 100 m and 17 m/s, 6 deg/s). The gyro blends bridge such pairs.", (0, 1000)))
    gyro_correction_max_ratio: float = field(default=1.5, metadata=meta(
        "The gyro's rates are corrected from the flow, and its bias learnt, only while its turn over the pair is at "
        "most this many times the median translational flow (both normalised units): a turn's rotational flow "
        "swamps the translational flow that tells a rate error from the FOE (at 100 m and 17 m/s, 3 deg/s).",
        (0, 100)))
    gyro_bias_tau_s: float = field(default=20.0, metadata=meta(
        "Time constant over which the pairs' rate corrections are averaged into the gyro's bias, which is then "
        "taken off its rates in every pair, s.", (0.1, 3600)))
    jerk_psd: float = field(default=0.2, metadata=meta(
        "White-jerk spectral density of the Doppler acceleration filter, m^2/s^5: lower is smoother but follows "
        "a bank change less (pseudo_attitude.DopplerAccelerationFilter); 0.2 gives the least roll error with "
        "`smoothing_lag_s` 0.6 at 5 or 10 Hz and 0.05 m/s Doppler noise (sitl/pseudo_attitude_eval.py).",
        (0.001, 1000)))
    lateral_window_s: float = field(default=0.25, metadata=meta(
        "With IMU samples: the accelerometer's lateral angle that turns the pseudo-roll to the airframe's is "
        "its mean over this long either side of the instant, s: about the spread of the smoothed Doppler "
        "acceleration's response (std 0.14 s at 10 Hz fixes, `jerk_psd` 0.2, `smoothing_lag_s` 0.6), so a gust's "
        "lateral jolt cancels between the two instead of entering the roll.", (0.0, 2.0)))
    gyro_roll_tau_s: float = field(default=3.0, metadata=meta(
        "With IMU samples: the roll is blended with the gyro's roll rate, following the gyro over spans shorter "
        "than this and the GNSS beyond, the gyro's bias estimated (pseudo_attitude.GyroAidedAngle), s; 0: the "
        "GNSS roll alone. The attitude then checks the autopilot's gyro only over longer spans; none is given for "
        "this long after the blend (re)starts.", (0, 60)))
    gyro_pitch_yaw_tau_s: float = field(default=3.0, metadata=meta(
        "With IMU samples: each path's pitch and yaw (the flow's, from pair to pair) are blended with the gyro's "
        "Euler rates, following the gyro over spans shorter than this and the flow beyond, the gyro's bias "
        "estimated (pseudo_attitude.GyroAidedAngle), s; 0: each pair's own. Pairs without an attitude (no focus "
        "of expansion) are bridged on the gyro alone for at most this long.", (0, 60)))
    smoothing_lag_s: float = field(default=0.6, metadata=meta(
        "The pseudo-attitude of an instant is smoothed with the GNSS fixes up to this long after it (fixed-lag "
        "Rauch-Tung-Striebel): the attitude still describes its instant but is given this much later, s "
        "(0: filtered, from the fixes up to the instant only; sitl/pseudo_attitude_eval.py measures both).", (0, 3)))
    min_fix_type: int = field(default=GNSS_3D, metadata=meta(
        "A fix is used from this MAVLink GPS_FIX_TYPE on (3 = 3-D), unless it reports jamming.", (2, 6)))
    min_speed_mps: float = field(default=5.0, metadata=meta(
        "Below this ground speed the course, and so the attitude, is undefined: nothing is given, m/s.", (0.5, 100)))
    max_lateral_deg: float = field(default=3.0, metadata=meta(
        "With an IMU: a lateral specific force beyond this angle from the body's -z (a slip or skid) flags the "
        "frame pair uncoordinated, and keeps the pseudo-roll out of the gyro roll blend over that span, degrees.",
        (0.1, 45)))
    max_drift_deg: float = field(default=10.0, metadata=meta(
        "Without an IMU: a drift angle (the FOE's yaw offset) beyond this flags the pair uncoordinated, degrees; "
        "a crosswind's crab counts too.", (0.1, 60)))
    max_pitch_offset_deg: float = field(default=20.0, metadata=meta(
        "A focus of expansion putting the velocity more than this above or below the body's x axis (an angle of "
        "attack past the stall) is a wrong fit: its pair gives no attitude, degrees. Derotated by the GNSS-derived "
        "rates in bank changes the flow gave a few such fits (40 to 120 deg), whose attitudes were off by up to "
        "180 deg (sitl/gnss_flow_flight_eval.py).", (1, 90)))
    min_depression_deg: float = field(default=5.0, metadata=meta(
        "Flow points at least this far below the horizon are ground for the height above it, degrees.", (0.5, 89)))
    agl_range_m: tuple[float, float] = field(default=(1.0, 100.0), metadata=meta(
        "Heights above ground sent as DISTANCE_SENSOR (also its min and max distance), m.", (0.1, 1000)))
    agl_sigma_fraction: float = field(default=0.1, metadata=meta(
        "1-sigma of the height above ground stated to the autopilot, as a fraction of it.", (0.001, 1)))
    flow_vectors_shown: int = field(default=200, metadata=meta(
        "Flow vectors on telemetry per frame pair, at most (every k-th valid one).", (0, 10000)))

    def validate(self) -> tuple[str, str] | None:
        if self.camera is None and self.flow is None:
            return "camera", "give a camera, a flow sensor (`flow`) or both"
        if (self.camera is None) != (self.calibration is None):
            return "calibration", "give it with `camera`, and only then"
        low, high = self.agl_range_m
        if low >= high:
            return "agl_range_m", "give [lowest, highest] with lowest < highest"
        return None

    def sensor_inputs(self) -> dict[str, str]:
        optional = {"camera": "camera", "flow": "flow", "imu_sensor": "imu"}
        return {"gnss": "gnss", **{key: kind for key, kind in optional.items() if getattr(self, key) is not None}}

    def moved(self, raw: dict[str, Any], offset: tuple[float, float], move_map: Callable[[str], str]) -> dict[str, Any]:
        """Unchanged: nothing in this section is a position."""
        return raw
