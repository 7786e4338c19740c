"""The two ways the ``gnss_flow`` pipeline gets its flow: a camera's frames through grid
Lucas-Kanade (:class:`CameraPath`), or a flow sensor's fields (:class:`FlowSensorPath`). Each path
has its own estimates' source, health component, telemetry stream, counters and pair in progress;
the chain from a pair's flow to the attitude is the pipeline's (companion/nav/gnss_flow/pipeline.py).

Units: flow points and vectors in normalised image coordinates of the path's camera (optical
frame, companion/calibration.py), or pixels where a name says ``_px``; times on the daemon clock, s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from companion.calibration import CameraCalibration
from companion.health import Health, State
from companion.messages import FlowField, Frame
from companion.nav.gnss_flow.config import GnssFlowConfig
from companion.nav.gnss_flow.flow import FocusOfExpansion, grid_flow, normalised_flow
from companion.nav.gnss_flow.pseudo_attitude import PseudoAttitude
from drivers.mount import OPTICAL_TO_SENSOR, Mount


@dataclass
class GnssFlowStats:
    """One flow path's counters."""

    frames: int = 0  # camera frames, or flow fields, received
    skipped_frames: int = 0  # camera frames within 1 / pair_rate_hz of the previous frame used
    flows: int = 0  # pairs whose flow gave a focus of expansion
    attitudes: int = 0  # attitude estimates given
    ranges: int = 0  # height-above-ground range estimates given
    uncoordinated: int = 0  # pairs flagged as an uncoordinated manoeuvre (no attitude given)
    refused: dict[str, int] = field(default_factory=dict)  # pairs without an attitude, per reason


@dataclass(frozen=True)
class Instant:
    """The GNSS at one capture instant of a flow path: the pseudo-attitude (None where undefined)."""

    t: float  # daemon clock, s
    pseudo: PseudoAttitude | None
    speed_mps: float  # GNSS ground-relative speed, 3-D, m/s (NaN without an estimate)
    refusal: str  # why ``pseudo`` is None ("" when it is not)


@dataclass(frozen=True)
class PairResult:
    """What one pair (two frames, or one flow field) gave (telemetry)."""

    t_capture: float  # the attitude's time, mid-interval, s
    pseudo_euler_rad: tuple[float, float, float]  # at t_capture
    points: np.ndarray  # (N, 2) valid flow start points as measured: px (camera), normalised (flow sensor)
    flows: np.ndarray  # (N, 2) their flows, in the same units
    status: str = ""
    rates_source: str = ""  # "imu" or "gnss" ("" when not reached)
    foe: FocusOfExpansion | None = None
    offsets_rad: tuple[float, float] | None = None  # (pitch offset, drift angle)
    coordinated: bool | None = None
    lateral_rad: float | None = None  # the coordination check's angle (IMU lateral angle, or the drift angle)
    euler_rad: tuple[float, float, float] | None = None
    depth_m: np.ndarray | None = None  # (N,) per valid point, NaN where unobservable
    agl_m: float | None = None


class FlowPath:
    """One way the pipeline gets its flow, with its own estimates' ``source``, health component
    ``nav:<source>``, telemetry stream, counters and pair in progress. A path turns the instants
    the pipeline stamps with the GNSS (:meth:`complete`) into pairs and measures their flow
    (:meth:`measure`); the rest of the chain is the pipeline's."""

    def __init__(self, source: str, cam_to_body: np.ndarray, min_flow_n: float, health: Health) -> None:
        self.source = source
        self.stream = source.replace(".", "_")  # a telemetry stream name is a lower-case word
        self.component = f"nav:{source}"
        self.cam_to_body = cam_to_body  # v_body = cam_to_body @ v_optical
        self.min_flow_n = min_flow_n  # shortest translational flow for the FOE, normalised units
        self.health = health
        self.stats = GnssFlowStats()
        self.offsets = (0.0, 0.0)  # the newest pair's (pitch offset, drift) rad: the GNSS rates' frame
        self.last_pair_s: float | None = None  # the later instant of the newest pair, s
        self.last_result: PairResult | None = None
        self.published: PairResult | None = None
        health.report(self.component, State.LOST, "waiting for GNSS fixes and flow")

    def refuse(self, reason: str) -> None:
        """Count a pair without an attitude and report the reason (health degraded)."""
        key = reason.split(":")[0]
        self.stats.refused[key] = self.stats.refused.get(key, 0) + 1
        self.health.report(self.component, State.DEGRADED, reason)

    def reset(self) -> None:
        """Forget the pair in progress (the GNSS did not come for it)."""

    def complete(self, instant: Instant, payload: Any) -> tuple[Instant, Instant, Any, Any] | str | None:
        """The pair ``instant`` (with its message part ``payload``) completes: (earlier and later
        instants, the payloads to :meth:`measure`), or why it is refused, or None (no pair yet)."""
        raise NotImplementedError

    def measure(self, earlier: Any, later: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(points, flows) (N, 2) each in normalised image coordinates, then (points, flows) as
        measured (for telemetry), of the valid flow of a pair."""
        raise NotImplementedError

    def telemetry_flow(self, result: PairResult, shown: slice) -> dict[str, Any]:
        """The path's own telemetry keys: the ``shown`` flow vectors and the FOE in its units."""
        raise NotImplementedError

    def flow_noise_n(self, flows_n: np.ndarray) -> np.ndarray:
        """(N,) 1-sigma noise of each measured flow vector of ``flows_n`` (N, 2), normalised units."""
        raise NotImplementedError


class CameraPath(FlowPath):
    """Camera frames -> grid Lucas-Kanade flow between consecutive frames, undistorted."""

    def __init__(self, source: str, cfg: GnssFlowConfig, calibration: CameraCalibration, mount: Mount,
                 health: Health) -> None:
        super().__init__(source, mount.rotation @ OPTICAL_TO_SENSOR, cfg.foe_min_flow_px / calibration.K[0, 0],
                         health)
        self.cfg = cfg
        self.calibration = calibration
        self._previous: tuple[Instant, np.ndarray] | None = None  # the newest frame's instant and grey image

    def reset(self) -> None:
        self._previous = None

    def complete(self, instant: Instant, payload: Frame) -> tuple[Instant, Instant, Any, Any] | str | None:
        grey = payload.image if payload.image.ndim == 2 else cv2.cvtColor(payload.image, cv2.COLOR_BGR2GRAY)
        previous, self._previous = self._previous, (instant, grey)
        if previous is None:
            return None
        size = grey.shape[::-1]
        if size != (self.calibration.width, self.calibration.height) or previous[1].shape != grey.shape:
            return (f"frame size {size[0]}x{size[1]}: the calibration is for "
                    f"{self.calibration.width}x{self.calibration.height}")
        return previous[0], instant, previous[1], grey

    def measure(self, earlier: np.ndarray, later: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        cfg = self.cfg
        flow = grid_flow(earlier, later, grid=tuple(cfg.grid), win=cfg.lk_window_px, levels=cfg.lk_levels,
                         fb_max_px=cfg.fb_max_px)
        points_px, flows_px = flow.points_px[flow.valid], flow.flows_px[flow.valid]
        return *normalised_flow(points_px, flows_px, self.calibration), points_px, flows_px

    def flow_noise_n(self, flows_n: np.ndarray) -> np.ndarray:
        """The tracker's pixel noise (``lk_sigma_px``) over the focal length, whatever the flow."""
        return np.full(len(flows_n), self.cfg.lk_sigma_px / self.calibration.K[0, 0])

    def telemetry_flow(self, result: PairResult, shown: slice) -> dict[str, Any]:
        foe_px = None
        if result.foe is not None:
            foe_px = self.calibration.project(np.append(result.foe.point_n, 1.0)[None, :])[0]
        return {"image_size": (self.calibration.width, self.calibration.height),
                "flow_points_px": result.points[shown], "flow_px": result.flows[shown], "foe_px": foe_px}


class FlowSensorPath(FlowPath):
    """A flow sensor's fields (:class:`FlowField`, normalised already): each one pair."""

    def __init__(self, source: str, cfg: GnssFlowConfig, mount: Mount, health: Health) -> None:
        super().__init__(source, mount.rotation @ OPTICAL_TO_SENSOR, cfg.foe_min_flow_n, health)
        self.angle_sigma_deg = cfg.flow_angle_sigma_deg
        self._earlier: Instant | None = None  # the newest instant stamped: the next field's earlier one
        self.last_queued_s = -math.inf  # the later instant of the newest field queued, s

    def reset(self) -> None:
        self._earlier = None

    def complete(self, instant: Instant, payload: FlowField | None) -> tuple[Instant, Instant, Any, Any] | None:
        """``payload`` None: the earlier instant of a field, kept; a field: its later instant (kept
        too: the next field's earlier instant when the fields follow each other)."""
        earlier, self._earlier = self._earlier, instant
        if payload is None or earlier is None or earlier.t != payload.t_earlier:  # no pair, or its start dropped
            return None
        return earlier, instant, None, payload

    def measure(self, earlier: None, later: FlowField) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        points, flows = later.points_n[later.valid], later.flows_n[later.valid]
        return points, flows, points, flows

    def flow_noise_n(self, flows_n: np.ndarray) -> np.ndarray:
        """The direction noise (``flow_angle_sigma_deg``) times each vector's measured length."""
        return math.radians(self.angle_sigma_deg) * np.linalg.norm(flows_n, axis=1)

    def telemetry_flow(self, result: PairResult, shown: slice) -> dict[str, Any]:
        return {"flow_points_n": result.points[shown], "flow_n": result.flows[shown]}
