"""The daemon's configuration: one YAML file mapped onto the dataclasses below.

Every key is documented here (``meta(doc=...)``); ``companion config-reference`` prints the
reference in docs/config.md from these definitions, and a test keeps the two identical.
Relative paths in the file (missions, worlds, key files) are resolved against the directory
of the config file; :meth:`Config.load_referenced` loads such a file and puts any error in it at
the config key (and line) that names it.
"""

from __future__ import annotations

from collections.abc import Callable
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml

from companion import plugins
from companion.schema import Document, SchemaError, load_text, meta, read_document

ConfigError = SchemaError
SENSOR_NAME = re.compile(r"[A-Za-z0-9_-]+")
T = TypeVar("T")


@dataclass
class VehicleConfig:
    sysid: int = field(default=1, metadata=meta("MAVLink system id of this companion (normally the autopilot's).", (1, 255)))
    compid: int = field(default=197, metadata=meta("MAVLink component id of this companion (197 = MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).", (1, 255)))
    autopilot_sysid: int = field(default=1, metadata=meta("System id of the autopilot to talk to.", (1, 255)))
    autopilot_compid: int = field(default=1, metadata=meta("Component id of the autopilot (1 = MAV_COMP_ID_AUTOPILOT1).", (1, 255)))


@dataclass
class StreamRatesConfig:
    """Rates (Hz) asked of the autopilot (SET_MESSAGE_INTERVAL, else legacy stream groups; the
    messages per need and their fallbacks: companion/mavlink/streams.py); 0 leaves a stream alone."""

    attitude: float = field(default=50.0, metadata=meta("ATTITUDE.", (0, 400)))
    imu: float = field(default=50.0, metadata=meta(
        "HIGHRES_IMU, else SCALED_IMU, RAW_IMU (ArduPilot) or SCALED_IMU2: the fusion's prediction input.", (0, 400)))
    local_position: float = field(default=10.0, metadata=meta("LOCAL_POSITION_NED.", (0, 100)))
    gps_raw: float = field(default=5.0, metadata=meta("GPS_RAW_INT (a gnss sensor with backend autopilot, instance 1).", (0, 50)))
    gps2_raw: float = field(default=0.0, metadata=meta(
        "GPS2_RAW: the autopilot's second receiver (a gnss sensor with backend autopilot, instance 2).", (0, 50)))
    home_position: float = field(default=0.5, metadata=meta("HOME_POSITION.", (0, 10)))
    pressure: float = field(default=0.0, metadata=meta(
        "SCALED_PRESSURE: the barometric altitude attached to IMU samples when the IMU message carries none "
        "(SCALED_IMU, RAW_IMU: ArduPilot 4.0 streams no HIGHRES_IMU); ekf_slam holds its height on it.", (0, 100)))
    estimator_status: float = field(default=2.0, metadata=meta("EKF_STATUS_REPORT (ArduPilot) / ESTIMATOR_STATUS (PX4).", (0, 50)))
    sim_state: float = field(default=0.0, metadata=meta(
        "Simulator ground truth: SIM_STATE, else SIMSTATE + SCALED_PRESSURE (simulators only; sim backends need it).",
        (0, 400)))


@dataclass
class MavlinkConfig:
    url: str = field(default="udpin:127.0.0.1:14550", metadata=meta(
        "Autopilot endpoint in pymavlink syntax: udpin:HOST:PORT, udpout:HOST:PORT, tcp:HOST:PORT, /dev/ttyAMA0,921600."))
    heartbeat_hz: float = field(default=1.0, metadata=meta("HEARTBEAT rate (MAV_TYPE_ONBOARD_CONTROLLER).", (0.2, 10)))
    estimate_rate_hz: float = field(default=30.0, metadata=meta(
        "Maximum VISION_POSITION_ESTIMATE / VISION_SPEED_ESTIMATE rate. ArduPilot needs >= 4 Hz, PX4 30-50 Hz.", (4, 100)))
    setpoint_rate_hz: float = field(default=10.0, metadata=meta("Setpoint keepalive rate while commanding.", (10, 100)))
    link_timeout_s: float = field(default=3.0, metadata=meta("No autopilot HEARTBEAT for this long = link lost.", (0.5, 60)))
    command_timeout_s: float = field(default=1.0, metadata=meta("Wait for COMMAND_ACK before a retry.", (0.05, 30)))
    command_retries: int = field(default=3, metadata=meta("Attempts per command before it is reported failed.", (1, 20)))
    autopilot_serial_port: int | None = field(default=None, metadata=meta(
        "The autopilot's SERIALn the companion is wired to (ArduPilot; e.g. 2 for TELEM2); `companion setup-autopilot` "
        "then also checks SERIALn_PROTOCOL 2 (MAVLink 2) and SERIALn_BAUD 921 (921600) on it. null = not checked.",
        (0, 9)))
    signing_key_file: str | None = field(default=None, metadata=meta(
        "MAVLink 2 signing: file holding the 32-byte secret key (raw, or 64 hex characters). null = unsigned."))
    command_sysids: tuple[int, ...] = field(default=(255,), metadata=meta(
        "Systems whose COMMAND_LONG addressed to this companion (vehicle.sysid / vehicle.compid) it obeys, e.g. "
        "MAV_CMD_NAV_RETURN_TO_LAUNCH for the EKF-SLAM return to base (255 = a ground station by convention; [] = "
        "none). Unsigned, anyone on the link can claim one: sign the link.", (1, 255)))
    streams: StreamRatesConfig = field(default_factory=StreamRatesConfig, metadata=meta("Streams requested from the autopilot."))


@dataclass
class OriginConfig:
    lat: float = field(metadata=meta("EKF origin latitude, degrees (WGS-84).", (-90, 90)))
    lon: float = field(metadata=meta("EKF origin longitude, degrees.", (-180, 180)))
    alt: float = field(metadata=meta("EKF origin altitude, metres AMSL.", (-500, 9000)))


@dataclass
class MountConfig:
    """Sensor pose in the body FRD frame."""

    position_m: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=meta("Offset from the body origin (FRD), metres.", (-5, 5)))
    rpy_deg: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=meta("Roll, pitch, yaw of the sensor frame relative to body FRD, degrees.", (-360, 360)))


@dataclass
class SensorConfig:
    kind: Literal["lidar", "camera", "imu", "gnss", "landmarks", "flow"] = field(metadata=meta(
        "What the sensor measures (flow: an optic-flow field in normalised image coordinates, no images)."))
    backend: str = field(metadata=meta(
        "Which backend reads it: real (the device), sim (simulated from ground truth; plugin sitl.sim_backends), "
        "replay (a recording), autopilot (the autopilot's own sensor over MAVLink), nmea (a serial NMEA "
        "receiver). `companion config-reference` lists the backends of each kind."))
    mount: MountConfig = field(default_factory=MountConfig, metadata=meta("Mount pose in the body frame."))
    settings: dict[str, Any] = field(default_factory=dict, metadata=meta(
        "Backend settings (port, model, file...), typed and checked by the backend: docs/config.md, Backends."))


@dataclass
class PipelinesConfig:
    fusion_rate_hz: float = field(default=50.0, metadata=meta("Rate of the fused output loop (the nav loop).", (10, 400)))
    sources: list[str] | None = field(default=None, metadata=meta(
        "Pose sources in priority order (pipeline names), as ArduPilot's EK3_SRC sets: the first one with a fresh "
        "estimate feeds the autopilot and the missions. null = the enabled pose pipelines in the order written."))
    source_timeout_s: float = field(default=0.3, metadata=meta(
        "A source with no estimate for this long is lost: the next one in `sources` takes over.", (0.05, 5)))
    source_return_s: float = field(default=2.0, metadata=meta(
        "A higher-priority source takes back over after being good (fresh, not degraded) this long without a break.",
        (0, 60)))
    source_max_sigma_m: float = field(default=1.0, metadata=meta(
        "A source whose horizontal position 1-sigma exceeds this is degraded: a good source in `sources` takes over "
        "(with none, the degraded one is still used).", (0.01, 1000)))
    attitude_alarm_deg: float = field(default=10.0, metadata=meta(
        "An attitude-only estimate differing from the autopilot's ATTITUDE by more than this (largest axis) ...", (0.5, 90)))
    attitude_alarm_s: float = field(default=2.0, metadata=meta(
        "... for this long raises the cross-check alarm (health crosscheck:<pipeline>, STATUSTEXT).", (0, 60)))
    sections: dict[str, Any] = field(default_factory=dict, metadata=meta(
        "One section per enabled pipeline, named as the pipeline (`lidar`, ...): its settings, typed by the pipeline "
        "(docs/config.md, Pipelines); null = off.", rest=True))
    enabled: dict[str, Any] = field(default_factory=dict, init=False, repr=False, compare=False)  # typed sections


@dataclass
class TelemetryConfig:
    enabled: bool = field(default=True, metadata=meta("Publish telemetry on zenoh."))
    mode: Literal["peer", "client"] = field(default="peer", metadata=meta("zenoh session mode."))
    listen: list[str] = field(default_factory=lambda: ["tcp/127.0.0.1:7447"], metadata=meta("zenoh listen endpoints."))
    connect: list[str] = field(default_factory=list, metadata=meta("zenoh endpoints to connect to."))
    multicast_scouting: bool = field(default=False, metadata=meta("zenoh multicast scouting (off: endpoints are explicit)."))
    gossip_scouting: bool = field(default=False, metadata=meta("zenoh gossip scouting."))
    queue_size: int = field(default=256, metadata=meta("Bounded publish queue; the oldest message is dropped when full.", (8, 100000)))
    pose_hz: float = field(default=20.0, metadata=meta("Pose/velocity publish rate.", (1, 50)))
    scan_hz: float = field(default=5.0, metadata=meta(
        "Horizontal scan (binary) with its extracted lines and matched corners: publish rate. The map follows every 2 s.", (2, 10)))
    setpoint_hz: float = field(default=10.0, metadata=meta(
        "Setpoint publish rate while commanding (like scan_hz and status_hz: published between nav cycles, at most at "
        "`pipelines.fusion_rate_hz`).", (1, 50)))
    status_hz: float = field(default=1.0, metadata=meta(
        "Health, link, autopilot, system, estimate_stats, rates and mission publish rate.", (0.2, 10)))
    dashboard_mode: Literal["peer", "client"] = field(default="peer", metadata=meta(
        "zenoh mode of `companion dashboard` (client: through a zenoh router)."))
    dashboard_connect: list[str] = field(default_factory=list, metadata=meta(
        "Endpoints `companion dashboard` connects to: the daemon's listen endpoint as the ground laptop reaches it "
        "(e.g. tcp/192.168.1.10:7447) or a router. Empty: the `listen` endpoints, 0.0.0.0 and [::] read as "
        "loopback (a dashboard on the same machine, as with `companion sitl`)."))


@dataclass
class RecordConfig:
    """The flight recorder (companion/recording/): MCAP files a user opens in Foxglove or replays with
    ``companion replay``. Off by default."""

    enabled: bool = field(default=False, metadata=meta(
        "Record every sensor message, estimate, source selection, MAVLink message in and out, telemetry and "
        "health change to MCAP files in `dir`."))
    dir: str = field(default="recordings", metadata=meta(
        "Directory of the recordings (relative: to the config file's); created if missing."))
    max_file_mb: float = field(default=256.0, metadata=meta(
        "A recording is split into parts of at most about this size (MB).", (1, 100000)))
    max_total_mb: float = field(default=4096.0, metadata=meta(
        "The recordings in `dir` are kept under this size (MB): the oldest parts are removed.", (2, 10000000)))
    chunk_kb: int = field(default=512, metadata=meta(
        "MCAP chunk size (kB, uncompressed): a chunk is compressed (zstd) and written when full.", (16, 65536)))
    flush_s: float = field(default=1.0, metadata=meta(
        "A chunk is written at least this often (s): a crash or power loss loses at most this much.", (0.1, 60)))
    queue_size: int = field(default=8192, metadata=meta(
        "Bounded queue between the daemon and the recorder's thread; a message that finds it full is dropped "
        "and counted.", (64, 1000000)))
    frame_rate_hz: float = field(default=10.0, metadata=meta(
        "Camera frames recorded per second and camera at most (0: every frame); lossless PNG, so a replay of "
        "a camera pipeline is exact when this is at least the camera's rate.", (0, 1000)))
    view_hz: float = field(default=10.0, metadata=meta(
        "Foxglove's views, at most this often: each scanner's scans as LaserScan, the pose sent to the autopilot as "
        "PoseInFrame (0: none); every scan and estimate is recorded exactly regardless.", (0, 1000)))
    mavlink: bool = field(default=True, metadata=meta("Record every MAVLink message in and out."))
    telemetry: bool = field(default=True, metadata=meta(
        "Record every telemetry message published (what the dashboard shows; its playback needs them)."))
    foxglove_server: bool = field(default=False, metadata=meta(
        "Also serve the recorder's channels live to the Foxglove app (its WebSocket protocol, foxglove-sdk), with or "
        "without `enabled`."))
    foxglove_host: str = field(default="127.0.0.1", metadata=meta(
        "Address of the Foxglove server (loopback by default; 0.0.0.0 lets a ground laptop connect)."))
    foxglove_port: int = field(default=8765, metadata=meta("TCP port of the Foxglove server (0: any free port).", (0, 65535)))


@dataclass
class SchedulingConfig:
    realtime_priority: int = field(default=0, metadata=meta(
        "SCHED_FIFO priority the daemon asks for at start, for every thread (1-99; 0: normal scheduling). The nav "
        "loop then wakes on time on a loaded board. Granted with CAP_SYS_NICE or an RLIMIT_RTPRIO at least this "
        "high (systemd/companion.service: LimitRTPRIO=10); refused (or on a single CPU): a warning, normal "
        "scheduling.", (0, 99)))


@dataclass
class LoggingConfig:
    level: Literal["debug", "info", "warning", "error"] = field(default="info", metadata=meta("Log level (the CLI's --log-level overrides)."))


@dataclass
class RptAxisConfig:
    """RPT design parameters of one channel (eq. 16): closed-loop poles at roots(p_i) / epsilon."""

    epsilon: float = field(default=1.0, metadata=meta("Bandwidth scale: the poles move as 1 / epsilon.", (0.05, 20)))
    omega_n: float = field(default=0.99, metadata=meta("Natural frequency of the pole pair, rad/s.", (0.01, 20)))
    zeta: float = field(default=0.707, metadata=meta("Damping of the pole pair.", (0.05, 10)))
    k_i: float = field(default=0.25, metadata=meta("Integral pole, 1/s (x, y only; the z channel has no room for it).", (0, 10)))


@dataclass
class ControlLimitsConfig:
    """Limits on the controller's output (the trajectory has its own, per mission step)."""

    speed_xy_mps: float = field(default=2.0, metadata=meta("Horizontal speed guard.", (0.1, 20)))
    accel_xy_mps2: float = field(default=2.5, metadata=meta("Horizontal acceleration reference norm.", (0.1, 20)))
    jerk_xy_mps3: float = field(default=5.0, metadata=meta("Rate limit on the horizontal acceleration reference.", (0.1, 100)))
    climb_mps: float = field(default=1.0, metadata=meta("Largest upward velocity reference.", (0.1, 10)))
    descent_mps: float = field(default=0.8, metadata=meta("Largest downward velocity reference.", (0.1, 10)))
    accel_z_mps2: float = field(default=2.0, metadata=meta("Rate limit on the vertical velocity reference.", (0.1, 20)))


@dataclass
class AutopilotGainsConfig:
    """The autopilot's own position-loop gains, used by ``control.output`` position_only and pos_vel."""

    pos_xy_p: float = field(default=1.0, metadata=meta("ArduPilot PSC_POSXY_P / PX4 MPC_XY_P, 1/s.", (0.1, 10)))
    vel_xy_p: float = field(default=2.0, metadata=meta("ArduPilot PSC_VELXY_P / PX4 MPC_XY_VEL_P_ACC, 1/s.", (0.1, 20)))
    pos_z_p: float = field(default=1.0, metadata=meta("ArduPilot PSC_POSZ_P / PX4 MPC_Z_P, 1/s.", (0.1, 10)))


@dataclass
class ControlConfig:
    """The outer loop that flies mission trajectories (companion/control/, Wang et al. section IV)."""

    rate_hz: float = field(default=50.0, metadata=meta(
        "Control loop and setpoint rate while flying a trajectory. At or below `pipelines.fusion_rate_hz` each "
        "control step runs right after a nav cycle, on the estimate it made; above it, on its own timer.", (10, 200)))
    law: Literal["rpt", "pid"] = field(default="rpt", metadata=meta(
        "rpt: the paper's robust and perfect tracking law; pid: the baseline with the same closed-loop poles and no "
        "feed-forward (for comparison flights)."))
    output: Literal["auto", "pos_vel_acc", "pos_vel", "position_only"] = field(default="auto", metadata=meta(
        "pos_vel_acc: reference position + velocity (z: the controller's) + the controller's acceleration as "
        "feed-forward (type_mask 3072); pos_vel: the same with the acceleration folded into the velocity through "
        "the autopilot's velocity gain (type_mask 3520, for firmware without acceleration targets: ArduPilot Copter "
        "< 4.1); position_only: a position target that makes the autopilot's own loop demand the controller's "
        "output (type_mask 3576), for autopilots or modes that take positions only; auto: pos_vel_acc where the "
        "firmware (AUTOPILOT_VERSION) takes it, else pos_vel."))
    xy: RptAxisConfig = field(default_factory=RptAxisConfig, metadata=meta("x and y channels (paper: 1, 0.99, 0.707, 0.25)."))
    z: RptAxisConfig = field(default_factory=lambda: RptAxisConfig(omega_n=0.559, zeta=2.0, k_i=0.0), metadata=meta(
        "z channel (paper: epsilon 1, omega_n 0.559, zeta 2)."))
    limits: ControlLimitsConfig = field(default_factory=ControlLimitsConfig, metadata=meta("Output limits."))
    autopilot_gains: AutopilotGainsConfig = field(default_factory=AutopilotGainsConfig, metadata=meta(
        "The autopilot's position-loop gains (position_only and pos_vel outputs)."))


@dataclass
class FailsafeConfig:
    estimate_timeout_s: float = field(default=0.5, metadata=meta(
        "No fused estimate for this long = estimate lost (ArduPilot's own external-nav timeout is 0.3 s).", (0.05, 5)))
    lost_hold_s: float = field(default=3.0, metadata=meta(
        "Estimate lost: brake and hold on the autopilot's own estimate at most this long, then LAND. "
        "An estimate back and healthy for 1 s before that resumes the flight.", (0, 60)))
    degraded_speed_factor: float = field(default=0.5, metadata=meta(
        "Estimate degraded (any nav component degraded): the trajectory is flown at this fraction of its speed.", (0.1, 1)))
    gnss_loss: Literal["return_to_base", "continue"] = field(default="return_to_base", metadata=meta(
        "A pipeline that flies the vehicle itself took over on GNSS loss (the EKF-SLAM return to base): "
        "return_to_base drops the mission's current step for its guidance (mission step return_to_base); "
        "continue ignores it (the mission flies on, on whatever pose source is selected)."))


@dataclass
class GeofenceConfig:
    """A box in the map frame (LOCAL_NED). Trajectories that leave it are refused before take-off of the step;
    the vehicle's estimate leaving it stops the flight and holds (the pilot decides what next)."""

    enabled: bool = field(default=True, metadata=meta("Check the geofence."))
    box_ned_m: tuple[tuple[float, float], tuple[float, float]] | None = field(default=None, metadata=meta(
        "[[x_min, y_min], [x_max, y_max]] metres; null = the bounds of the lidar map (pipelines.lidar.map); "
        "neither: no companion geofence (logged; the autopilot's own FENCE_* still apply)."))
    inset_m: float = field(default=0.3, metadata=meta("The fence lies this far inside the box (walls are solid).", (0, 10)))
    ceiling_m: float = field(default=3.0, metadata=meta("Highest allowed height above the origin, metres.", (0.2, 1000)))


@dataclass
class PayloadConfig:
    command: Literal["servo", "gripper"] = field(default="servo", metadata=meta(
        "servo: MAV_CMD_DO_SET_SERVO (ArduPilot: an output with SERVOn_FUNCTION 0); gripper: MAV_CMD_DO_GRIPPER "
        "release (ArduPilot GRIP_ENABLE, PX4 payload deliverer)."))
    servo: int = field(default=9, metadata=meta("Servo output number for command servo.", (1, 32)))
    release_pwm: int = field(default=1900, metadata=meta("PWM (us) that releases the payload.", (500, 2500)))
    gripper: int = field(default=1, metadata=meta("Gripper instance for command gripper.", (1, 8)))


@dataclass
class MissionConfig:
    file: str | None = field(default=None, metadata=meta("Mission YAML to fly at start (relative to this file). null = fly nothing."))
    allow_arm: bool = field(default=False, metadata=meta("Whether the companion may arm the vehicle. Off for real vehicles unless you mean it."))
    failsafe: FailsafeConfig = field(default_factory=FailsafeConfig, metadata=meta("What the mission does when the estimate degrades or is lost."))
    geofence: GeofenceConfig = field(default_factory=GeofenceConfig, metadata=meta("Where trajectories may go."))
    payload: PayloadConfig = field(default_factory=PayloadConfig, metadata=meta("How the payload_drop step releases the payload."))
    on_daemon_stop: Literal["land", "hold"] = field(default="land", metadata=meta(
        "The daemon stopping while the mission commands the vehicle in flight: land = a hold target, then LAND "
        "(indoors the estimate stops with the daemon; a fixed wing: RTL, it has no LAND mode); hold = only the hold target (ArduPilot GUIDED keeps it on "
        "its own estimate, e.g. GPS)."))


def _sitl_error_sources() -> dict[str, float]:
    # Motor-on IMU noise and sensor biases, as a flying multicopter's IMU sees them (ArduPilot's
    # default_params/copter.parm zeroes them for repeatable autotests).
    return {"SIM_ACC_RND": 0.5, "SIM_GYR_RND": 0.5, "SIM_ACC_BIAS_X": 0.05, "SIM_ACC_BIAS_Y": -0.03,
            "SIM_ACC_BIAS_Z": 0.04}


@dataclass
class ParameterEvent:
    """An ArduPilot parameter the harness sets at a flight time (a fault injected into the autopilot)."""

    at_s: float = field(metadata=meta("When: seconds since the flight's start (the report's time line).", (0, 1e6)))
    name: str = field(metadata=meta("Parameter name, e.g. AHRS_TRIM_Y (pitch trim, rad)."))
    value: float = field(metadata=meta("Value, in the parameter's own unit."))


@dataclass
class ArduPilotSitlConfig:
    """ArduPilot SITL as the vehicle of `companion sitl` (or `--ardupilot PATH`), instead of the built-in one."""

    binary: str | None = field(default=None, metadata=meta(
        "ArduPilot SITL executable (e.g. ../shared/ardupilot/arducopter), relative to this file; null = the built-in "
        "vehicle. `companion sitl --ardupilot PATH` overrides it."))
    model: str = field(default="+", metadata=meta("SITL --model (frame): + or x quad, hexa, ..."))
    defaults: str | None = field(default=None, metadata=meta(
        "ArduPilot default parameter file for the model, relative to this file; null = the .parm beside the binary "
        "named after it (copter.parm for arducopter)."))
    parameters: dict[str, float] = field(default_factory=_sitl_error_sources, metadata=meta(
        "Parameters the harness sets after the companion's own (error sources of the simulated sensors: SIM_ACC_RND, "
        "SIM_GYR_RND, biases, wind). The barometer's are always zeroed: it is the truth altimeter."))
    parameter_events: list[ParameterEvent] = field(default_factory=list, metadata=meta(
        "Parameters set during the flight, each {at_s, name, value}: PARAM_SET on the harness's own link, e.g. "
        "AHRS_TRIM_Y 0.26 (the autopilot's pitch off by 15 deg, unknown to it: it flies on it) and back to 0."))


@dataclass
class InFlightStart:
    """A fixed wing started in the air: level, at ``start``'s position and heading."""

    height_m: float = field(metadata=meta("Height above the origin, m.", (5, 2000)))
    airspeed_mps: float = field(metadata=meta("Airspeed, m/s (the simulated plane cruises at 17).", (10, 40)))


@dataclass
class SimEvent:
    """A scripted disturbance of the built-in vehicle while ``start_s <= t < end_s`` (simulation time)."""

    start_s: float = field(metadata=meta("Start, simulation seconds.", (0, 1e6)))
    end_s: float = field(metadata=meta("End, simulation seconds.", (0, 1e6)))
    sideslip_deg_s: float = field(default=0.0, metadata=meta(
        "vehicle: plane only: rudder held, a yaw rate added to the turn coordination: uncoordinated (slipping) "
        "flight, deg/s.", (-30, 30)))
    tilt_fault_deg: tuple[float, float] = field(default=(0.0, 0.0), metadata=meta(
        "The autopilot's attitude estimate wrong by this (roll, pitch), degrees, unknown to it: it flies on it "
        "(a failing gyro, a board moved in its mount).", (-45, 45)))

    def validate(self) -> tuple[str, str] | None:
        if self.end_s <= self.start_s:
            return "end_s", "must be after start_s"
        return None


@dataclass
class SitlConfig:
    """Used only by `companion sitl` (the harness), never by the daemon on a vehicle."""

    world: str = field(default="worlds/arena.yaml", metadata=meta("World YAML (relative to this file)."))
    vehicle: Literal["copter", "plane"] = field(default="copter", metadata=meta(
        "The built-in simulated vehicle: copter = ArduCopter-like quadrotor, plane = ArduPlane-like fixed wing "
        "(ArduPlane modes; it takes off from a runway at `start` along its heading)."))
    vehicle_url: str = field(default="udpin:127.0.0.1:14555", metadata=meta(
        "Where the simulated vehicle listens for the companion (the daemon gets the matching udpout URL)."))
    gcs_urls: list[str] = field(default_factory=lambda: ["udpout:127.0.0.1:14550"], metadata=meta(
        "Extra vehicle links for a ground station (QGroundControl, mavsdk)."))
    gps: bool = field(default=True, metadata=meta("Simulate a GPS receiver (the indoor default does not fuse it)."))
    position_source: Literal["extnav", "gps"] = field(default="gps", metadata=meta(
        "What the simulated autopilot fuses for position (EK3_SRC1_POSXY): extnav = the companion's estimate."))
    start: tuple[float, float, float] | None = field(default=None, metadata=meta(
        "Start pose: north m, east m, yaw deg. null = the world's `start`."))
    start_in_flight: InFlightStart | None = field(default=None, metadata=meta(
        "vehicle: plane only: {height_m, airspeed_mps}: start flying level at `start` along its heading (armed, "
        "in FBWA, wings level; a mission's mode step switches to GUIDED) instead of on the runway; null = on the "
        "ground."))
    wind_ned_mps: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=meta("Mean wind, NED m/s.", (-20, 20)))
    events: list[SimEvent] = field(default_factory=list, metadata=meta(
        "Scripted disturbances of the built-in vehicle (not ArduPilot SITL's), each {start_s, end_s (simulation "
        "seconds), sideslip_deg_s (plane only: rudder held, a yaw rate added to the turn coordination, deg/s), "
        "tilt_fault_deg ([roll, pitch]: the autopilot's attitude estimate wrong by this, unknown to it)}."))
    gust_mps: float = field(default=0.2, metadata=meta("Gust standard deviation, m/s.", (0, 10)))
    tick_s: float = field(default=0.005, metadata=meta("Lockstep tick (simulation seconds per clock step).", (0.001, 0.05)))
    scip_sensors: list[str] = field(default_factory=list, metadata=meta(
        "Sensors (names in `sensors`: lidars with backend real, settings.host 127.0.0.1, settings.model "
        "UTM-30LX or URG-04LX, one settings.tcp_port each) that the SCIP bridge (python -m sitl.scip_bridge) "
        "emulates from the vehicle's ground truth, so the real Hokuyo driver runs end to end. Real time only."))
    ardupilot: ArduPilotSitlConfig = field(default_factory=ArduPilotSitlConfig, metadata=meta(
        "ArduPilot SITL as the vehicle (real time only)."))

    def validate(self) -> tuple[str, str] | None:
        if self.start_in_flight is not None and self.vehicle != "plane":
            return "start_in_flight", "only the fixed wing (vehicle: plane) starts in flight"
        for i, event in enumerate(self.events):
            if event.sideslip_deg_s and self.vehicle != "plane":
                return f"events[{i}].sideslip_deg_s", "only the fixed wing (vehicle: plane) slips on command"
        return None


@dataclass
class Config:
    origin: OriginConfig = field(metadata=meta("EKF origin sent to the autopilot (SET_GPS_GLOBAL_ORIGIN + SET_HOME_POSITION)."))
    vehicle: VehicleConfig = field(default_factory=VehicleConfig, metadata=meta("MAVLink identities."))
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig, metadata=meta("The autopilot link."))
    plugins: list[str] = field(default_factory=list, metadata=meta(
        "Python modules imported first that register more sensor backends or pipelines (e.g. sitl.sim_backends, "
        "the simulated sensors; docs/extending.md)."))
    sensors: dict[str, SensorConfig] = field(default_factory=dict, metadata=meta("Sensors by name."))
    pipelines: PipelinesConfig = field(default_factory=PipelinesConfig, metadata=meta("Navigation pipelines."))
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig, metadata=meta("zenoh telemetry."))
    logging: LoggingConfig = field(default_factory=LoggingConfig, metadata=meta("Logging."))
    scheduling: SchedulingConfig = field(default_factory=SchedulingConfig, metadata=meta(
        "CPU scheduling of the daemon's process."))
    record: RecordConfig = field(default_factory=RecordConfig, metadata=meta("Flight recorder (MCAP)."))
    control: ControlConfig = field(default_factory=ControlConfig, metadata=meta("Trajectory-following controller."))
    mission: MissionConfig = field(default_factory=MissionConfig, metadata=meta("Mission to fly."))
    sitl: SitlConfig = field(default_factory=SitlConfig, metadata=meta("Simulation harness settings."))
    base_dir: Path = field(default=Path("."), init=False, repr=False)
    source: str = field(default="<string>", init=False, repr=False)
    document: Document | None = field(default=None, init=False, repr=False, compare=False)  # for line_of
    # {key path: file} of every file load_referenced loaded (the recorder keeps a copy of each), and
    # files to read instead of what a key names (a replay reads the copies kept in its recording)
    referenced: dict[str, Path] = field(default_factory=dict, init=False, repr=False, compare=False)
    file_overrides: dict[str, Path] = field(default_factory=dict, init=False, repr=False, compare=False)

    def validate(self) -> tuple[str, str] | None:
        for name in self.sensors:
            if not SENSOR_NAME.fullmatch(name):
                return f"sensors.{name}", "a sensor name is letters, digits, '_' and '-' (it is part of key paths and topics)"
        if any(s.backend == "sim" for s in self.sensors.values()) and self.mavlink.streams.sim_state <= 0:
            return "mavlink.streams.sim_state", "simulated sensors render from SIM_STATE ground truth: ask for it (e.g. 50)"
        for i, module in enumerate(self.plugins):
            try:
                plugins.load([module])
            except ImportError as exc:
                return f"plugins[{i}]", f"cannot import {module!r}: {exc}"
        plugins.load()
        return (self._check_sensors() or self._check_gnss_streams() or self._check_pipelines()
                or self._check_scip_sensors())

    def _check_sensors(self) -> tuple[str, str] | None:
        """Every sensor's backend exists and its settings are what the backend takes."""
        for name, sensor in self.sensors.items():
            entry = plugins.backend(sensor.kind, sensor.backend)
            if entry is None:
                known = ", ".join(e.backend for e in plugins.backends() if e.kind == sensor.kind) or "none"
                hint = "; simulated backends come with the plugin sitl.sim_backends (add it to `plugins`)" \
                    if sensor.backend == "sim" else ""
                return f"sensors.{name}.backend", f"no {sensor.kind} backend {sensor.backend!r} (known: {known}){hint}"
            try:
                typed(sensor.settings, entry.settings)
            except SchemaError as exc:
                return f"sensors.{name}.settings" + (f".{exc.key_path}" if exc.key_path else ""), exc.message
        return None

    def _check_gnss_streams(self) -> tuple[str, str] | None:
        """An autopilot gnss sensor's message is asked of the autopilot."""
        for name, sensor in self.sensors.items():
            if sensor.kind == "gnss" and sensor.backend == "autopilot":
                second = sensor.settings.get("instance", 1) == 2
                key, message = ("gps2_raw", "GPS2_RAW") if second else ("gps_raw", "GPS_RAW_INT")
                if getattr(self.mavlink.streams, key) <= 0:
                    return f"mavlink.streams.{key}", f"sensor {name} reads {message} from the autopilot: ask for it (e.g. 5)"
        return None

    def _check_pipelines(self) -> tuple[str, str] | None:
        """Every pipeline section names a registered pipeline, is valid, and names sensors of the right kind;
        every source is an enabled pipeline. Fills ``pipelines.enabled`` with the typed sections."""
        p = self.pipelines
        p.enabled = {}
        for name, raw in p.sections.items():
            entry = plugins.pipeline(name)
            if entry is None:
                known = ", ".join(e.name for e in plugins.pipelines()) or "none"
                return f"pipelines.{name}", f"no pipeline {name!r} (known: {known})"
            if raw is None:
                continue
            try:
                section = typed(raw, entry.config)
            except SchemaError as exc:
                return f"pipelines.{name}" + (f".{exc.key_path}" if exc.key_path else ""), exc.message
            for key, kind in section.sensor_inputs().items():
                sensor_name = getattr(section, key)
                sensor = self.sensors.get(sensor_name)
                if sensor is None or sensor.kind != kind:
                    return (f"pipelines.{name}.{key}",
                            f"{sensor_name!r} is not a {kind} in `sensors` ({', '.join(self.sensors) or 'none'})")
            p.enabled[name] = section
        for i, name in enumerate(p.sources or []):
            if name not in p.enabled or not plugins.pipeline(name).poses:
                posing = ", ".join(n for n in p.enabled if plugins.pipeline(n).poses) or "none"
                return f"pipelines.sources[{i}]", f"{name!r} is not an enabled pose pipeline ({posing})"
        return None

    def source_priority(self) -> list[str]:
        """The pose sources in priority order (``pipelines.sources``, or every enabled pipeline that
        produces poses, in the order written)."""
        if self.pipelines.sources is not None:
            return list(self.pipelines.sources)
        return [name for name in self.pipelines.enabled if plugins.pipeline(name).poses]

    def _check_scip_sensors(self) -> tuple[str, str] | None:
        """sitl.scip_sensors: real lidars on loopback, on distinct ports (the harness checks the model)."""
        ports: dict[int, str] = {}
        for i, name in enumerate(self.sitl.scip_sensors):
            key = f"sitl.scip_sensors[{i}]"
            if name in self.sitl.scip_sensors[:i]:
                return key, f"{name!r} is named twice"
            sensor = self.sensors.get(name)
            if sensor is None or sensor.kind != "lidar" or sensor.backend != "real":
                return key, f"{name!r} is not a lidar with backend: real in `sensors`"
            settings = sensor.settings
            if settings.get("host") != "127.0.0.1":
                return key, f"sensor {name!r}: the SCIP bridge listens on loopback: set settings.host: 127.0.0.1"
            port = int(settings.get("tcp_port", 10940))
            if port in ports:
                return key, f"sensor {name!r}: settings.tcp_port {port} is also {ports[port]!r}'s"
            ports[port] = name
        return None

    def resolve(self, relative: str) -> Path:
        """A path from the config file, resolved against the file's directory."""
        p = Path(relative)
        return p if p.is_absolute() else self.base_dir / p

    def line_of(self, key_path: str) -> int | None:
        """The line of ``key_path`` (e.g. ``mission.file``) in the config file; None for a config
        not loaded from a file."""
        return self.document.line_of(key_path) if self.document is not None else None

    def load_referenced(self, key_path: str, value: str, loader: Callable[[Path], T]) -> T:
        """``loader(path)`` for the file named ``value``, which the key ``key_path`` (e.g.
        ``mission.file``, ``sensors.lidar.settings.file``) holds, resolved against the config's directory.

        What the loader raises about the file (SchemaError: its content, naming its own file, line and key;
        OSError: it cannot be read; ValueError: its content, naming the file) is raised again as a
        ConfigError at this config file, the key's line and the key, with the loader's message after it.
        A file in :attr:`file_overrides` under ``key_path`` is read instead of ``value``'s.
        """
        path = self.file_overrides.get(key_path) or self.resolve(value)
        try:
            loaded = loader(path)
            self.referenced[key_path] = path
            return loaded
        except SchemaError as exc:
            raise self._error_at(key_path, str(exc)) from exc
        except OSError as exc:
            raise self._error_at(key_path, f"{path}: cannot read file: {exc.strerror or exc}") from exc
        except ValueError as exc:
            raise self._error_at(key_path, str(exc)) from exc

    def _error_at(self, key_path: str, message: str) -> ConfigError:
        return ConfigError(self.source, key_path, self.line_of(key_path), message)


def load_config(path: str | Path) -> Config:
    """Load and validate a config file; raises :class:`ConfigError` (file, key path, line)."""
    document = read_document(path)
    cfg = document.build(Config)
    cfg.base_dir = Path(path).resolve().parent
    cfg.source = str(path)
    cfg.document = document
    return cfg


def typed(raw: Any, schema: type[T]) -> T:
    """A settings mapping (``sensors.<name>.settings``, ``pipelines.<name>``) as its typed dataclass;
    SchemaError with the key path relative to the mapping."""
    return load_text(yaml.safe_dump({} if raw is None else raw), schema)
