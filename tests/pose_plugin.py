"""A second pose pipeline, defined only in the tests: it proves the seam (docs/extending.md).

``gnss_pose``: the position of a GNSS receiver (WGS-84 -> LOCAL_NED at the config's origin),
shifted by ``offset_ned_m`` so that a switch to it is a visible jump, with the attitude of an
IMU sensor. It touches nothing but this file: a config enables it with
``plugins: [tests.pose_plugin]`` and a ``pipelines.gnss_pose`` section.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.frames import ned_from_geodetic
from companion.messages import Estimate, GnssFix, ImuSample, PoseEstimate
from companion.pipeline import PipelineContext
from companion.plugins import register_pipeline
from companion.schema import meta
from companion.timing import Timings


@dataclass
class GnssPoseConfig:
    """``pipelines.gnss_pose``: a pose from a GNSS receiver and an IMU (tests only)."""

    gnss_sensor: str = field(metadata=meta("Name (in `sensors`) of the receiver."))
    imu_sensor: str = field(default="imu", metadata=meta("Name (in `sensors`) of the IMU (attitude)."))
    offset_ned_m: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0), metadata=meta(
        "Added to every position, m (makes a switch to this source visible).", (-100, 100)))
    position_sigma_m: float | None = field(default=None, metadata=meta(
        "1-sigma position error claimed, m; null = the receiver's accuracies.", (0.001, 100)))

    def sensor_inputs(self) -> dict[str, str]:
        return {"gnss_sensor": "gnss", "imu_sensor": "imu"}

    def moved(self, raw: dict[str, Any], offset: tuple[float, float], move_map: Callable[[str], str]) -> dict[str, Any]:
        return raw  # positions come from the origin, which moves with the frame


class GnssPose:
    name = "gnss_pose"
    telemetry_streams: tuple[str, ...] = ()

    def __init__(self, cfg: GnssPoseConfig, origin: tuple[float, float, float]) -> None:
        self.cfg = cfg
        self.origin = origin
        self.timings = {"gnss_pose": Timings()}
        self.fixes = 0
        self._fix: GnssFix | None = None
        self._euler = (0.0, 0.0, 0.0)

    def subscriptions(self) -> dict[str, Callable[[Any], None]]:
        return {self.cfg.gnss_sensor: self._on_fix, self.cfg.imu_sensor: self._on_imu}

    def _on_fix(self, fix: GnssFix) -> None:
        if fix.has_position:
            self._fix = fix

    def _on_imu(self, sample: ImuSample) -> None:
        if sample.euler_rad is not None:
            self._euler = sample.euler_rad

    def step(self, now: float) -> list[Estimate]:
        fix, self._fix = self._fix, None
        if fix is None:
            return []
        self.fixes += 1
        position = ned_from_geodetic(fix.lat_deg, fix.lon_deg, fix.alt_m, self.origin) + np.array(self.cfg.offset_ned_m)
        h = self.cfg.position_sigma_m or fix.h_acc_m or 2.0
        v = self.cfg.position_sigma_m or fix.v_acc_m or 3.0
        covariance = np.diag([h * h, h * h, v * v, 0.01, 0.01, 0.01])
        return [PoseEstimate(fix.t_capture, position, self._euler, covariance, source=self.name)]

    def snapshot(self) -> dict[str, Any]:
        return {"fixes": self.fixes}

    def telemetry(self, static_due: bool) -> dict[str, dict[str, Any]]:
        return {}

    def operating_area(self) -> None:
        return None


@register_pipeline("gnss_pose", GnssPoseConfig)
def _build(section: GnssPoseConfig, ctx: PipelineContext) -> GnssPose:
    o = ctx.config.origin
    return GnssPose(section, (o.lat, o.lon, o.alt))
