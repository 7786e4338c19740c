"""The ``gnss_flow`` pipeline through its handlers and ``step``: synthetic GNSS fixes of a
coordinated turn and camera frames rendered (cv2.warpPerspective) of a textured flat ground from
the true camera poses.

Scenario: 25 m/s level turn banked 20 deg at 40 m above the ground, angle of attack 3 deg, a
forward camera pitched 30 deg down (90 x 74 deg field of view, 320 x 240; the horizon in view,
untextured sky above it), frames at 30 Hz (the pipeline uses every third), fixes at 10 Hz
(0.02 m/s Doppler noise). Frames: NED world (ground at D = 0), body FRD.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from companion import plugins
from companion.calibration import CameraCalibration
from companion.config import ConfigError, load_config
from companion.frames import GRAVITY_MPS2, euler_from_rotation, rotation_from_euler, wrap_pi
from companion.health import Health, State
from companion.messages import GNSS_3D, AttitudeEstimate, Frame, GnssFix, ImuSample, RangeEstimate
from companion.nav.gnss_flow.pipeline import GnssFlowConfig, GnssFlowPipeline
from companion.pipeline import PipelineContext
from drivers.mount import OPTICAL_TO_SENSOR, Mount

REPO = Path(__file__).resolve().parent.parent
SPEED = 25.0  # m/s
BANK = math.radians(20.0)
ALPHA = math.radians(3.0)  # angle of attack (still air)
HEIGHT = 40.0  # m above the ground
TURN_RATE = GRAVITY_MPS2 * math.tan(BANK) / SPEED  # rad/s, coordinated
WIDTH, HEIGHT_PX = 320, 240
FX = (WIDTH / 2) / math.tan(math.radians(45.0))  # 90 deg horizontal field of view
CALIBRATION = CameraCalibration(WIDTH, HEIGHT_PX, np.array([[FX, 0, (WIDTH - 1) / 2], [0, FX, (HEIGHT_PX - 1) / 2],
                                                           [0, 0, 1]]), np.zeros(5))
MOUNT = Mount(rotation_from_euler(0.0, math.radians(-30.0), 0.0), np.zeros(3))  # forward, 30 deg down
SUPERSAMPLE = 4
SKY = 200  # grey level above the horizon (no texture: not tracked)
FRAME_DT = 1 / 30  # the camera; the pipeline uses every third frame (pair_rate_hz 10)
FIX_DT = 0.1
TEXTURE_M_PER_PX = 0.25
TEXTURE_PX = 2400
# roll, pitch, yaw against truth (the roll's error is the pseudo-roll's: up to 0.46 deg here), the
# flow derotated by the IMU's gyro, or by the GNSS-derived rates with the spin about the direction
# of travel re-estimated from the flow (without: drift angle errors up to 2.5 deg)
TOLERANCE_DEG = {"imu": 0.6, "gnss": 0.8}
AGL_TOLERANCE = 0.10  # relative


def texture() -> np.ndarray:
    """Smoothed random ground texture, uint8, seeded."""
    rng = np.random.default_rng(3)
    noise = rng.normal(128.0, 60.0, (TEXTURE_PX, TEXTURE_PX)).astype(np.float32)
    return np.clip(cv2.GaussianBlur(noise, (0, 0), 3.0) * 4 - 3 * 128, 0, 255).astype(np.uint8)


GROUND = texture()


def course(t: float) -> float:
    return TURN_RATE * t


def velocity(t: float) -> np.ndarray:
    return SPEED * np.array([math.cos(course(t)), math.sin(course(t)), 0.0])


def position(t: float) -> np.ndarray:
    radius = SPEED / TURN_RATE
    return np.array([radius * math.sin(course(t)), radius * (1 - math.cos(course(t))), -HEIGHT])


def body_to_ned(t: float, slip_rad: float = 0.0, roll_error_rad: float = 0.0) -> np.ndarray:
    """The airframe: the velocity's frame (bank, no climb, course) pitched up by the angle of
    attack; ``slip_rad`` yaws the nose left of the velocity and ``roll_error_rad`` rolls it off the
    bank (an uncoordinated manoeuvre: the specific force no longer in the body's x-z plane)."""
    wind = rotation_from_euler(BANK + roll_error_rad, 0.0, course(t))
    return wind @ rotation_from_euler(0.0, 0.0, -slip_rad) @ rotation_from_euler(0.0, ALPHA, 0.0)


def render(t: float, **attitude: float) -> np.ndarray:
    """The camera's image of the textured ground at time ``t`` (s), rendered at ``SUPERSAMPLE``
    times the resolution and averaged down (no aliasing of the far ground)."""
    cam_to_ned = body_to_ned(t, **attitude) @ MOUNT.rotation @ OPTICAL_TO_SENSOR
    r_cn = cam_to_ned.T
    translation = -r_cn @ position(t)
    k = CALIBRATION.K.copy()
    k[:2] *= SUPERSAMPLE
    k[:2, 2] += (SUPERSAMPLE - 1) / 2  # pixel centres at integers
    ground_to_image = k @ np.column_stack((r_cn[:, 0], r_cn[:, 1], translation))
    half = TEXTURE_PX * TEXTURE_M_PER_PX / 2  # the texture centred beside the turn's start
    texture_to_ground = np.array([[0.0, TEXTURE_M_PER_PX, -half + 60.0], [TEXTURE_M_PER_PX, 0.0, -half + 60.0],
                                  [0.0, 0.0, 1.0]])  # (column, row) -> (north, east)
    size = (WIDTH * SUPERSAMPLE, HEIGHT_PX * SUPERSAMPLE)
    image = cv2.warpPerspective(GROUND, ground_to_image @ texture_to_ground, size, flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_REFLECT)
    u, v = np.meshgrid(np.arange(size[0]), np.arange(size[1]))
    rays = np.stack((u, v, np.ones_like(u)), axis=-1) @ np.linalg.inv(k).T
    image[rays @ cam_to_ned[2] <= 0] = SKY  # at or above the horizon (the homography mirrors the ground there)
    return cv2.resize(image, (WIDTH, HEIGHT_PX), interpolation=cv2.INTER_AREA)


def imu_sample(t: float, **attitude: float) -> ImuSample:
    """The autopilot's IMU: the specific force and turn rate of the body of :func:`body_to_ned`."""
    r_nb = body_to_ned(t, **attitude)
    accel_ned = SPEED * TURN_RATE * np.array([-math.sin(course(t)), math.cos(course(t)), 0.0])
    specific_force = r_nb.T @ (accel_ned - np.array([0.0, 0.0, GRAVITY_MPS2]))
    return ImuSample(t, specific_force, r_nb.T @ np.array([0.0, 0.0, TURN_RATE]))


def run(pipeline: GnssFlowPipeline, frames: int = 13, imu: bool = False, stamp_late_s: float = 0.0,
        **attitude: float) -> list[AttitudeEstimate | RangeEstimate]:
    """Fixes from 5 s before the first frame to after the last (stamped ``stamp_late_s`` after
    their epoch: a backend that did not remove the receiver's latency), the frames, the IMU at
    100 Hz if ``imu``, fed in order of arrival (a fix 0.1 s after its epoch) with a nav cycle per
    message."""
    rng = np.random.default_rng(0)
    fix_times = np.arange(-5.0, frames * FRAME_DT + 0.5, FIX_DT)
    events = [(t + 0.1, "fix", t) for t in fix_times]
    events += [(i * FRAME_DT + 0.005, "frame", i * FRAME_DT) for i in range(frames)]
    if imu:
        events += [(t, "imu", t) for t in np.arange(-0.5, frames * FRAME_DT + 0.5, 0.01)]
    out = []
    for arrival, kind, t in sorted(events):
        if kind == "fix":
            v = velocity(t) + rng.normal(0.0, 0.02, 3)
            pipeline.on_fix(GnssFix("gps", t + stamp_late_s, GNSS_3D, 0.0, 0.0, 0.0, velocity_ned_mps=v,
                                    speed_acc_mps=0.02))
        elif kind == "frame":
            pipeline.on_frame(Frame("cam", t, render(t, **attitude), sequence=round(t / FRAME_DT)))
        else:
            pipeline.on_imu(imu_sample(t, **attitude))
        out += pipeline.step(arrival)
    return out


def make(**settings: object) -> tuple[GnssFlowPipeline, Health]:
    health = Health(lambda: 0.0)
    cfg = GnssFlowConfig(gnss="gps", camera="cam", calibration="unused.yaml", **settings)
    return GnssFlowPipeline(cfg, CALIBRATION, MOUNT, health), health


def check_attitudes(estimates: list, tolerance_deg: float) -> list[AttitudeEstimate]:
    attitudes = [e for e in estimates if isinstance(e, AttitudeEstimate)]
    assert attitudes
    for a in attitudes:
        truth = np.degrees(euler_from_rotation(body_to_ned(a.t_capture)))
        error = [math.degrees(wrap_pi(math.radians(x - y))) for x, y in zip(np.degrees(a.euler_rad), truth)]
        assert np.all(np.abs(error) < tolerance_deg), (error, a.t_capture)
        assert np.all(np.isfinite(a.covariance)) and np.all(np.diag(a.covariance) > 0)
    return attitudes


@pytest.mark.parametrize("imu", [False, True], ids=["gnss_rates", "imu"])
def test_a_coordinated_turn_gives_the_attitude_and_the_height_above_ground(imu: bool) -> None:
    pipeline, health = make(imu_sensor="imu" if imu else None)
    estimates = run(pipeline, imu=imu)
    attitudes = check_attitudes(estimates, TOLERANCE_DEG["imu" if imu else "gnss"])
    assert len(attitudes) == 4  # every pair of the five frames used (of 13)
    assert pipeline.stats.skipped_frames == 8
    ranges = [e for e in estimates if isinstance(e, RangeEstimate)]
    assert len(ranges) == 4
    for r in ranges:
        tilt = body_to_ned(r.t_capture)[2, 2]  # along the body's down axis to flat ground
        assert r.orientation == "down" and abs(r.distance_m * tilt - HEIGHT) < AGL_TOLERANCE * HEIGHT
        assert math.isfinite(r.variance_m2) and r.variance_m2 > 0
    for e in estimates:  # nothing NaN
        values = [e.distance_m] if isinstance(e, RangeEstimate) else list(e.euler_rad)
        assert all(math.isfinite(v) for v in values)
    assert pipeline.stats.uncoordinated == 0 and pipeline.stats.attitudes == 4
    assert health.get("nav:gnss_flow").state == State.OK
    telemetry = pipeline.telemetry(False)["gnss_flow"]
    assert telemetry["rates_source"] == ("imu" if imu else "gnss")
    assert telemetry["coordinated"] is True and telemetry["foe_px"] is not None
    assert abs(telemetry["pitch_offset_rad"] - ALPHA) < math.radians(TOLERANCE_DEG["imu" if imu else "gnss"])
    assert len(telemetry["flow_px"]) <= 200 and telemetry["depth_m"]["count"] > 100
    assert pipeline.telemetry(False) == {}  # once per pair


def test_an_uncoordinated_turn_is_flagged_and_gives_no_attitude() -> None:
    """Skidding: the airframe rolled 10 deg less than the lift's bank and yawed 4 deg: the IMU's
    lateral specific force flags every pair."""
    pipeline, health = make(imu_sensor="imu")
    estimates = run(pipeline, imu=True, slip_rad=math.radians(4.0), roll_error_rad=math.radians(-10.0))
    assert estimates == []
    assert pipeline.stats.uncoordinated == 4
    component = health.get("nav:gnss_flow")
    assert component.state == State.DEGRADED and "uncoordinated" in component.reason
    assert pipeline.telemetry(False)["gnss_flow"]["coordinated"] is False


def test_without_an_imu_a_large_drift_angle_is_flagged() -> None:
    pipeline, health = make(max_drift_deg=3.0)
    estimates = run(pipeline, frames=7, slip_rad=math.radians(6.0))
    assert estimates == [] and pipeline.stats.uncoordinated == 2
    assert "drift" in health.get("nav:gnss_flow").reason


SENSORS = ("origin: {lat: 1.0, lon: 2.0, alt: 3.0}\n"
           "sensors:\n"
           "  gps: {kind: gnss, backend: autopilot}\n"
           "  imu: {kind: imu, backend: autopilot}\n"
           "  cam: {kind: camera, backend: real, settings: {device: 0}, mount: {rpy_deg: [0, -30, 0]}}\n")


def test_the_registry_builds_it_from_a_config(tmp_path: Path) -> None:
    shutil.copy(REPO / "config" / "cameras" / "down-60-640.yaml", tmp_path / "cam.yaml")
    config = tmp_path / "c.yaml"
    config.write_text(SENSORS + "pipelines:\n"
                      "  gnss_flow: {gnss: gps, camera: cam, calibration: cam.yaml, imu_sensor: imu}\n")
    cfg = load_config(config)
    entry = plugins.pipeline("gnss_flow")
    assert entry is not None and not entry.poses
    pipeline = entry.build(cfg.pipelines.enabled["gnss_flow"], PipelineContext(cfg, Health(lambda: 0.0)))
    assert set(pipeline.subscriptions()) == {"gps", "cam", "imu"}
    assert np.allclose(pipeline.cam_to_body @ [0.0, 0.0, 1.0], [math.cos(math.radians(30)), 0.0,
                                                                 math.sin(math.radians(30))])


@pytest.mark.parametrize("key, value", [("camera", "imu"), ("gnss", "cam"), ("imu_sensor", "gps")])
def test_a_sensor_of_another_kind_is_refused(tmp_path: Path, key: str, value: str) -> None:
    section = {"gnss": "gps", "camera": "cam", "calibration": "cam.yaml", key: value}
    config = tmp_path / "c.yaml"
    written = ", ".join(f"{k}: {v}" for k, v in section.items())
    config.write_text(SENSORS + "pipelines:\n  gnss_flow: {" + written + "}\n")
    with pytest.raises(ConfigError) as exc:
        load_config(config)
    assert f"pipelines.gnss_flow.{key}" in str(exc.value) and "is not a" in str(exc.value)


def test_receiver_latency_is_compensated() -> None:
    """Fixes stamped 0.2 s late (a backend that did not remove the receiver's latency): with
    receiver_latency_s the estimates are those of correctly stamped fixes; without, the yaw is
    off (the course of 0.2 s later is 1.6 deg on in this turn; the frame, captured before the
    newest fix fused, takes the estimate at that fix: 0.7 deg here)."""
    reference = run(make()[0], frames=4)
    compensated = run(make(receiver_latency_s=0.2)[0], frames=4, stamp_late_s=0.2)
    late = run(make()[0], frames=4, stamp_late_s=0.2)
    for a, b, c in zip(reference, compensated, late):
        assert a.t_capture == b.t_capture == c.t_capture
    yaw = [e.euler_rad[2] for e in (reference[0], compensated[0], late[0])]
    assert abs(yaw[1] - yaw[0]) < 1e-9
    assert abs(math.degrees(yaw[2] - yaw[0])) > 0.5


def test_frames_of_another_size_than_the_calibration_are_refused_and_no_pairs_lose_the_health() -> None:
    pipeline, health = make()
    for t in np.arange(-2.0, 0.01, FIX_DT):
        pipeline.on_fix(GnssFix("gps", t, GNSS_3D, 0.0, 0.0, 0.0, velocity_ned_mps=velocity(t), speed_acc_mps=0.02))
    for t in (0.0, 0.1):
        pipeline.on_frame(Frame("cam", t - 0.1, np.zeros((HEIGHT_PX // 2, WIDTH // 2), np.uint8)))
    assert pipeline.step(0.1) == []
    assert "calibration is for 320x240" in health.get("nav:gnss_flow").reason
    pipeline.step(2.5)
    assert health.get("nav:gnss_flow").state == State.LOST
