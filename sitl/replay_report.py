"""The flight report of a replayed recording (``companion replay FILE.mcap --report R.json``).

A recording made by ``companion sitl --record DIR --report ...`` has a scoring file beside it
(``sitl-<id>.mcap``, :func:`write_scoring_file`): what the harness scored the flight's report from
(the vehicle's flight log with the truth, the daemon's telemetry, the run's figures) and the world.
The replay's report is that report scored again with the replayed estimates put where the flight's
were: each VISION_POSITION_ESTIMATE the autopilot received (matched by its capture stamp) carries
the replayed pose as the wire carries it (float32), and each attitude cross-check the replayed
attitude. So it equals the flight's report exactly when the replay equals the flight, and shows what
a changed pipeline would have scored on the same flight otherwise.

Without a scoring file (a recording from a real vehicle: no truth) the report has the schema's
fields with the truth-scored ones null, the rest from the recorded telemetry.
"""

from __future__ import annotations

import json
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from mcap.records import Attachment, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from companion.config import ControlConfig
from companion.messages import AttitudeEstimate, PoseEstimate
from companion.recording.reader import Recording
from companion.recording.replay import Cycle, ReplayResult
from companion.world import load_world
from sitl.flight_log import FlightLog
from sitl.report import build_report

SCORING_METADATA = "sitl.report_inputs"
WORLD_ATTACHMENT = "sitl.world"


def scoring_path(directory: Path, recording_id: str) -> Path:
    return directory / f"sitl-{recording_id[:8]}.mcap"


def write_scoring_file(directory: Path, recording_id: str, inputs: dict[str, Any], world_file: Path) -> Path:
    """Keep ``inputs`` (build_report's keyword arguments but ``ground_height``) and the world beside
    the recording ``recording_id``; the file's path."""
    path = scoring_path(directory, recording_id)
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start("", "uav-companion")
        writer.add_metadata(SCORING_METADATA, {"recording_id": recording_id, "inputs": json.dumps(inputs)})
        writer.add_attachment(log_time=0, create_time=0, name=WORLD_ATTACHMENT, media_type="application/yaml",
                              data=world_file.read_bytes())
        writer.finish()
    return path


def read_scoring_file(recording: Recording) -> tuple[dict[str, Any], bytes] | None:
    """(inputs, world file content) of ``recording``'s scoring file, None if it has none."""
    path = scoring_path(recording.parts[0].parent, recording.id)
    if not path.is_file():
        return None
    inputs = world = None
    with open(path, "rb") as f:
        for record in StreamReader(f).records:
            if isinstance(record, Metadata) and record.name == SCORING_METADATA:
                if record.metadata.get("recording_id") != recording.id:
                    return None
                inputs = json.loads(record.metadata["inputs"])
            elif isinstance(record, Attachment) and record.name == WORLD_ATTACHMENT:
                world = bytes(record.data)
    return (inputs, world) if inputs is not None and world is not None else None


def replay_report(recording: Recording, result: ReplayResult) -> dict[str, Any]:
    """The flight report of the replay, with its ``replay`` block (module docstring)."""
    scoring = read_scoring_file(recording)
    if scoring is None:
        report = _report_without_truth(recording, result)
    else:
        inputs, world_text = scoring
        inputs["log"] = with_replayed_poses(inputs["log"], result.replayed)
        inputs["attitude_checks"] = with_replayed_attitudes(inputs["attitude_checks"], result.replayed)
        with tempfile.NamedTemporaryFile(suffix=".yaml") as f:
            f.write(world_text)
            f.flush()
            world = load_world(Path(f.name))
        inputs["origin"] = tuple(inputs["origin"])
        inputs["base_ne"] = tuple(inputs["base_ne"]) if inputs.get("base_ne") is not None else None
        report = build_report(**inputs, ground_height=world.floor_height_at)
    report["replay"] = result.summary()
    return report


def _wire(x: float) -> float | None:
    """A value as a MAVLink float field carries it and the flight log keeps it (NaN: None)."""
    v = float(np.float32(x))
    return v if math.isfinite(v) else None


def with_replayed_poses(log: dict[str, Any], cycles: list[Cycle]) -> dict[str, Any]:
    """The flight log with each received VISION_POSITION_ESTIMATE's pose, attitude and position
    covariance taken from the replayed pose forwarded with the same capture stamp (usec)."""
    forwarded: dict[int, PoseEstimate] = {}
    for cycle in cycles:
        for e in cycle.estimates:
            if isinstance(e, PoseEstimate) and e.source == cycle.selected:
                forwarded[int(round(e.t_capture * 1e6))] = e
    vp = log["vision_position"]
    for i, usec in enumerate(vp["usec"]):
        e = forwarded.get(int(usec))
        if e is None:
            continue
        c = e.pose_covariance
        vp["pos_ned"][i] = [_wire(v) for v in e.position_ned]
        vp["euler_rad"][i] = [_wire(v) for v in e.euler_rad]
        vp["position_covariance"][i] = [_wire(c[0, 0]), _wire(c[0, 1]), _wire(c[0, 2]), _wire(c[1, 1]),
                                        _wire(c[1, 2]), _wire(c[2, 2])]
    return log


def with_replayed_attitudes(checks: list[dict[str, Any]], cycles: list[Cycle]) -> list[dict[str, Any]]:
    """The attitude cross-checks with each estimate's angles taken from the replayed attitude estimate
    of the same source and capture stamp (telemetry's JSON: NaN as null)."""
    replayed = {(e.source, e.t_capture): e for cycle in cycles for e in cycle.estimates if isinstance(e, AttitudeEstimate)}
    out = []
    for check in checks:
        e = replayed.get((check["source"], check["t_capture"]))
        if e is not None:
            check = {**check, "euler_rad": [v if math.isfinite(v) else None for v in e.euler_rad]}
        out.append(check)
    return out


def _report_without_truth(recording: Recording, result: ReplayResult) -> dict[str, Any]:
    """The report's schema from the recording alone: no truth, so the scored fields are null; the
    mission, control law and the daemon's own figures from the recorded config and telemetry."""
    empty = FlightLog(seed=0, lockstep=False, monotonic_at_sim_zero=None).to_dict(0.0)
    config = yaml.safe_load(recording.config_yaml) or {}
    mission = Path(str((config.get("mission") or {}).get("file") or "none")).stem
    law = (config.get("control") or {}).get("law") or ControlConfig().law
    seconds = result.recorded[-1].now - result.recorded[0].now if result.recorded else 0.0
    return build_report(mission=mission, seconds=seconds, lockstep=False, seed=0, control_law=law, log=empty,
                        telemetry=result.last_telemetry, origin=(math.nan, math.nan, math.nan), cpu_percent=None, rss_mb=None,
                        attitude_checks=[], ground_height=lambda north, east: 0.0)
