"""A simulated beam-calibration sweep: the frames a user records for ``companion laser-dots calibrate``.

The vehicle is carried over the floor markers from low to high (heights evenly from
``--low`` to ``--high`` m), a few degrees of tilt and any heading, and the config's simulated
downward camera (``pipelines.laser_dots.camera``, ``backend: sim``, with its true ``laser_beams``
rig, mounting errors included) renders one frame at each pose. The frames are written as PNG
images, ``0000.png`` on, to the output folder: what a recording of the camera would hold.

    python -m sitl.calibration_sweep -c config/sitl-laser-dots-89.yaml --out /tmp/sweep
    companion laser-dots calibrate -c config/sitl-laser-dots-89.yaml /tmp/sweep

Poses: north within ``--north`` (m, over the config's world), east -0.3..1.8 m, roll and pitch
N(0, 3 deg), heading within +/-30 deg; seeded (``--seed``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from companion.config import Config, load_config, typed
from companion.frames import quat_from_euler
from companion.world import load_world
from drivers.mount import Mount
from sitl.camera_sim import SimCameraSettings, SimulatedCamera
from sitl.sim_backends import camera_calibration
from sitl.truth import TruthSample

Pose = tuple[np.ndarray, np.ndarray]  # NED position m, quaternion [w, x, y, z] body FRD -> NED


class _NoTruth:
    """A truth source that has nothing: a camera made to render given poses is never read()."""

    def at(self, t: float) -> None:
        return None


NO_TRUTH = _NoTruth()


def sweep_poses(n: int, low_m: float, high_m: float, north_m: tuple[float, float], seed: int) -> list[Pose]:
    """``n`` poses from ``low_m`` to ``high_m`` above the floor (see the module docstring)."""
    rng = np.random.default_rng(seed)
    poses = []
    for height in np.linspace(low_m, high_m, n):
        position = np.array([rng.uniform(*north_m), rng.uniform(-0.3, 1.8), -height])
        rpy = np.radians([rng.normal(0.0, 3.0), rng.normal(0.0, 3.0), rng.uniform(-30.0, 30.0)])
        poses.append((position, quat_from_euler(*rpy)))
    return poses


def laser_dots_camera(cfg: Config) -> SimulatedCamera:
    """The simulated camera of ``cfg``'s laser_dots pipeline over ``cfg``'s simulated world, for
    rendering at given poses (no truth stream: :meth:`SimulatedCamera.render` only)."""
    name = cfg.pipelines.enabled["laser_dots"].camera
    sensor = cfg.sensors[name]
    settings = typed(sensor.settings, SimCameraSettings)
    world = cfg.load_referenced("sitl.world", cfg.sitl.world, load_world)
    return SimulatedCamera(name, settings, camera_calibration(cfg, name, settings), Mount.from_config(sensor.mount),
                           world, NO_TRUTH)


def write_sweep(camera: SimulatedCamera, poses: list[Pose], out: Path) -> int:
    """Render a frame at every pose into ``out`` (created) as NNNN.png; the number written."""
    out.mkdir(parents=True, exist_ok=True)
    for k, (position, quat) in enumerate(poses):
        frame = camera.render(0.0, TruthSample(0.0, position, np.zeros(3), quat), None, k)
        cv2.imwrite(str(out / f"{k:04d}.png"), frame.image)
    return len(poses)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-c", "--config", required=True, help="a config with pipelines.laser_dots on a sim camera")
    parser.add_argument("--out", required=True, help="folder for the frames (NNNN.png)")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--low", type=float, default=0.4, help="lowest height of the body origin, m")
    parser.add_argument("--high", type=float, default=1.8, help="highest, m")
    parser.add_argument("--north", type=float, nargs=2, default=(1.0, 8.0), help="north range of the poses, m")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    cfg = load_config(args.config)
    count = write_sweep(laser_dots_camera(cfg), sweep_poses(args.frames, args.low, args.high, tuple(args.north), args.seed),
                        Path(args.out))
    print(f"{args.out}: {count} frames")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
