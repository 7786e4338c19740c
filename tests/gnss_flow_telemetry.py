"""What a daemon running the ``gnss_flow`` pipeline with a camera and a flow sensor publishes, made
by the real pipeline and the real attitude cross-check: the coordinated turn of
tests/test_gnss_flow_pipeline.py (13 camera frames and 4 flow fields), its estimates checked
against an autopilot whose ATTITUDE is the truth plus a roll error. The dashboard tests publish it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

from companion.crosscheck import AttitudeCrossCheck
from companion.frames import euler_from_rotation
from companion.messages import AttitudeEstimate
from tests.test_gnss_flow_pipeline import body_to_ned, make, run

ALARM_DEG = 5.0  # the cross-check's threshold (pipelines.attitude_alarm_deg)
ALARM_HOLD_S = 0.0  # and hold: the second divergent estimate of a source raises the alarm


@dataclass(frozen=True)
class FlowTelemetry:
    streams: dict[str, dict[str, Any]]  # gnss_flow (flow sensor), gnss_flow_images (camera): each newest pair
    checks: tuple[dict[str, Any], ...]  # the newest attitude_check of each source
    health: dict[str, Any]  # the health message (nav:* and crosscheck:* components)


@cache
def flight(autopilot_roll_error_deg: float) -> FlowTelemetry:
    """The pipeline's telemetry after the turn, with the cross-check against an autopilot rolled
    ``autopilot_roll_error_deg`` off the truth (beyond ALARM_DEG: the alarm of both sources)."""
    pipeline, health = make(camera=True, flow=True)
    estimates = [e for e in run(pipeline, frames=13, flows=4) if isinstance(e, AttitudeEstimate)]
    reference: list[tuple[float, float, float]] = []
    checks: dict[str, dict[str, Any]] = {}
    # the truth at the estimate's capture time, whether the cross-check asks with that time or without one
    crosscheck = AttitudeCrossCheck(lambda *_: reference[-1], health,
                                    lambda stream, message: checks.__setitem__(message["source"], message),
                                    ALARM_DEG, ALARM_HOLD_S)
    for estimate in estimates:
        roll, pitch, yaw = euler_from_rotation(body_to_ned(estimate.t_capture))
        reference.append((roll + math.radians(autopilot_roll_error_deg), pitch, yaw))
        crosscheck.submit(estimate)
    streams = pipeline.telemetry(False)
    assert set(streams) == {"gnss_flow", "gnss_flow_images"} and set(checks) == {"gnss_flow", "gnss_flow.images"}
    return FlowTelemetry(streams, tuple(checks.values()), health.snapshot())
