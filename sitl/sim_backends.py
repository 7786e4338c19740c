"""The simulated sensor backends, as a plugin (``plugins: [sitl.sim_backends]`` in a config).

Importing this module registers every ``backend: sim`` with the service's registry
(companion/plugins.py). They render from the simulator's ground truth (SIM_STATE/SIMSTATE over
the autopilot link, :class:`sitl.truth.TruthSource`, one per daemon) and see the world of
``sitl.world``. The service itself never imports the simulator: only a config that names this
plugin brings it in.
"""

from __future__ import annotations

from typing import Any

from companion.calibration import CameraCalibration, load_calibration
from companion.config import typed
from companion.plugins import register_backend
from companion.world import World, load_world
from drivers.mount import Mount
from sitl.camera_lens import check_lens
from sitl.camera_scene import check_marker_ids
from sitl.camera_sim import SimCameraSettings, SimulatedCamera
from sitl.flow_sim import SimFlowSettings, SimulatedFlowSensor
from sitl.gnss_sim import SimGnssSettings, SimulatedGnss
from sitl.landmark_sensor import SimLandmarkSettings, SimulatedLandmarkSensor
from sitl.lidar_sim import SimLidarSettings, SimulatedLidar
from sitl.truth import TruthSource


def sim_world(ctx: Any) -> World:
    """The world of ``sitl.world`` (loaded once per daemon)."""
    cfg = ctx.config
    return ctx.once("sim_world", lambda: cfg.load_referenced("sitl.world", cfg.sitl.world, load_world))


def truth(ctx: Any) -> TruthSource:
    """The simulator's ground truth over the autopilot link (one per daemon)."""
    return ctx.once("truth", lambda: TruthSource(ctx.link, ctx.config.origin))


def _check_world(cfg: Any, name: str) -> None:
    cfg.load_referenced("sitl.world", cfg.sitl.world, load_world)


@register_backend("lidar", "sim", SimLidarSettings, check_files=_check_world)
def _lidar(name: str, settings: SimLidarSettings, ctx: Any) -> SimulatedLidar:
    """A scanner ray-cast in the world from the truth pose."""
    return SimulatedLidar(name, settings, Mount.from_config(ctx.config.sensors[name].mount), sim_world(ctx), truth(ctx))



def camera_calibration(cfg: Any, name: str, settings: SimCameraSettings) -> CameraCalibration:
    """The intrinsics of camera ``name``: its calibration file, or what its settings describe."""
    if settings.calibration is None:
        return settings.intrinsics()
    return cfg.load_referenced(f"sensors.{name}.settings.calibration", settings.calibration,
                               lambda path: check_lens(load_calibration(path)))


def _check_camera(cfg: Any, name: str) -> None:
    cfg.load_referenced("sitl.world", cfg.sitl.world, lambda path: check_marker_ids(load_world(path)))
    camera_calibration(cfg, name, typed(cfg.sensors[name].settings, SimCameraSettings))


@register_backend("camera", "sim", SimCameraSettings, check_files=_check_camera)
def _camera(name: str, settings: SimCameraSettings, ctx: Any) -> SimulatedCamera:
    """A camera rendering the world's floor, markers and walls from the truth pose."""
    cfg = ctx.config
    return SimulatedCamera(name, settings, camera_calibration(cfg, name, settings), Mount.from_config(cfg.sensors[name].mount),
                           sim_world(ctx), truth(ctx))


@register_backend("gnss", "sim", SimGnssSettings)
def _gnss(name: str, settings: SimGnssSettings, ctx: Any) -> SimulatedGnss:
    """A receiver fixing the truth position around the configured EKF origin."""
    origin = ctx.config.origin
    return SimulatedGnss(name, settings, (origin.lat, origin.lon, origin.alt), truth(ctx))


@register_backend("landmarks", "sim", SimLandmarkSettings, check_files=_check_world)
def _landmarks(name: str, settings: SimLandmarkSettings, ctx: Any) -> SimulatedLandmarkSensor:
    """The seed's vision sensor: range and bearings to the world's point landmarks in its cone."""
    mount = Mount.from_config(ctx.config.sensors[name].mount)
    return SimulatedLandmarkSensor(name, settings, mount, sim_world(ctx).landmarks, truth(ctx))


@register_backend("flow", "sim", SimFlowSettings)
def _flow(name: str, settings: SimFlowSettings, ctx: Any) -> SimulatedFlowSensor:
    """The GNSS + optic-flow seed's synthetic flow map: the exact motion field over flat ground, angle noise."""
    return SimulatedFlowSensor(name, settings, Mount.from_config(ctx.config.sensors[name].mount), truth(ctx))
