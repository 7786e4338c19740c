"""``companion replay FILE.mcap``: a flight recording's sensor streams through the same pipelines,
in recorded order, and the replayed estimates next to the recorded ones.

The pipelines are built from the recorded config, reading the recorded copies of the files it
named (maps, worlds), by the same registry the daemon uses (:func:`companion.navloop.build_pipelines`)
and stepped by the same :class:`~companion.navloop.NavLoop` cycle: each sensor message goes to the
pipelines' handlers, each recorded nav cycle is run again at its recorded time, and a recorded
source command or guidance request is given again where it happened. Nothing else reaches the
pipelines in the daemon either (they do no I/O and read no clock), so the replay is deterministic:
the same recording gives the same estimates, bit for bit, and equal to the recorded ones unless the
recording lost messages (its queue was full: ``dropped``; frames over ``record.frame_rate_hz``) or
the pipeline code changed since. :func:`write_estimates` puts the replayed estimates next to the
recorded ones in an MCAP file (``--estimates``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

from companion.config import load_config
from companion.health import Health
from companion.messages import AttitudeEstimate, Estimate, PoseEstimate, RangeEstimate
from companion.navloop import NavLoop, NavOutputs, build_pipelines, build_selector
from companion.pipeline import GuidanceSource
from companion.recording import codec
from companion.recording.mcap_files import LIBRARY, PROFILE
from companion.recording.reader import Recording, RecordingError
from companion.recording.recorder import EVENT_SCHEMAS
from companion.sdnotify import WatchdogGate

SCHEMA_TYPES: dict[str, type] = {codec.message_schema(cls).name: cls for cls in codec.MESSAGE_TYPES.values()}
REPLAYED_TOPICS_PREFIX = ("/sensors/", "/nav/cycle", "/nav/source_command", "/nav/guidance_request")


@dataclass
class Cycle:
    """One nav cycle: its time, the estimates made in it, the pose source forwarded (None: none)."""

    now: float
    estimates: list[Estimate]
    selected: str | None


@dataclass
class ReplayResult:
    """The replay's cycles beside the recorded ones, and their differences."""

    pipelines: list[str]
    messages: int = 0  # recorded messages fed to the replay (sensor messages, cycles, commands)
    replayed: list[Cycle] = field(default_factory=list)
    recorded: list[Cycle] = field(default_factory=list)
    mismatched_cycles: int = 0  # cycles whose estimates (or selected source) are not bit for bit the recorded
    max_position_diff_m: float | None = None  # over the pose estimates of every cycle
    max_yaw_diff_deg: float | None = None  # over the pose and attitude estimates (where both have a yaw)
    max_range_diff_m: float | None = None  # over the range estimates
    first_mismatch_t: float | None = None  # the recorded time (s) of the first cycle that differs
    truncated_parts: list[str] = field(default_factory=list)
    recorder_dropped: dict[str, int] = field(default_factory=dict)
    first_part: int = 1  # > 1: the recording's first parts were removed (size cap): replayed from mid-flight
    last_telemetry: dict[str, dict[str, Any]] = field(default_factory=dict)  # {stream: its last recorded message}

    def summary(self) -> dict[str, Any]:
        """The report's ``replay`` block (issue 16's contract names: messages, max_position_diff_m, max_yaw_diff_deg)."""
        return {"messages": self.messages, "cycles": len(self.replayed), "pipelines": self.pipelines,
                "max_position_diff_m": self.max_position_diff_m, "max_yaw_diff_deg": self.max_yaw_diff_deg,
                "max_range_diff_m": self.max_range_diff_m, "mismatched_cycles": self.mismatched_cycles,
                "exact": self.mismatched_cycles == 0, "first_mismatch_t": self.first_mismatch_t,
                "truncated_parts": self.truncated_parts, "recorder_dropped": self.recorder_dropped,
                "first_part": self.first_part}


def replay(recording: Recording, pipelines: list[str] | None = None, speed: float | None = None) -> ReplayResult:
    """Replay ``recording`` through its config's pipelines (only ``pipelines`` if given; their
    estimates alone are compared). ``speed``: pace the replay at this multiple of recorded time
    (None: as fast as it runs). RecordingError for a recording that cannot be replayed."""
    with recording.temporary_directory() as tmp:
        directory = Path(tmp)
        cfg = load_config(recording.materialise_config(directory))
        cfg.file_overrides = recording.file_overrides(directory)
        unknown = sorted(set(pipelines or ()) - set(cfg.pipelines.enabled))
        if unknown:
            raise RecordingError(f"--pipelines {', '.join(unknown)}: not a pipeline of the recorded config "
                                 f"({', '.join(cfg.pipelines.enabled) or 'none'})")
        replay_time = [0.0]
        health = Health(lambda: replay_time[0])
        built = build_pipelines(cfg, health, pipelines)
        names = [p.name for p in built]
        handlers: dict[str, list] = {}
        for pipeline in built:
            for sensor, handler in pipeline.subscriptions().items():
                handlers.setdefault(sensor, []).append(handler)
        selector = build_selector(cfg, built)
        nop = lambda *args: None  # noqa: E731 (the replay sends nothing anywhere)
        nav = NavLoop(built, selector, NavOutputs(pose=nop, range=nop, attitude=nop, publish=nop),
                      WatchdogGate(max_age=math.inf, clock=lambda: replay_time[0]), cfg.pipelines.fusion_rate_hz,
                      lambda: replay_time[0])
        result = ReplayResult(pipelines=names, first_part=recording.first_part)
        nav.on_cycle = lambda now, made, chosen: result.replayed.append(
            Cycle(now, made, chosen.source if chosen is not None else None))
        guide = next((p for p in built if isinstance(p, GuidanceSource)), None)
        pace = Pacer(speed)
        for msg in recording.messages():
            if msg.topic.startswith("/telemetry/"):
                result.last_telemetry[msg.topic.removeprefix("/telemetry/")] = msg.doc
            if not msg.topic.startswith(REPLAYED_TOPICS_PREFIX):
                continue
            replay_time[0] = msg.t
            pace.wait_for(msg.t)
            result.messages += 1
            if msg.topic.startswith("/sensors/"):
                for handler in handlers.get(msg.topic.removeprefix("/sensors/"), ()):
                    handler(codec.decode_message(SCHEMA_TYPES[msg.schema], msg.doc))
            elif msg.topic == "/nav/cycle":
                recorded = [codec.decode_estimate(e) for e in msg.doc["estimates"]]
                result.recorded.append(Cycle(codec.unexact(msg.doc["now"]), recorded, msg.doc["selected"]))
                nav.cycle(result.recorded[-1].now)
            elif msg.topic == "/nav/source_command" and selector is not None:
                selector.command(msg.doc["source"])
            elif msg.topic == "/nav/guidance_request" and guide is not None:
                guide.request_guidance(msg.t, msg.doc["reason"])
        result.truncated_parts = [p.name for p in recording.truncated]
        result.recorder_dropped = dict(recording.stats.get("dropped") or {})
        compare(result, set(names))
        return result


def write_estimates(result: ReplayResult, path: Path) -> None:
    """The replayed estimates next to the recorded ones, as an MCAP file to open in Foxglove beside
    the recording: ``/recorded/nav/cycle`` and ``/replayed/nav/cycle`` (companion.NavCycle, every
    estimate), ``/recorded/nav/pose`` and ``/replayed/nav/pose`` (foxglove.PoseInFrame, the pose
    selected), at each cycle's time."""
    cycle_schema = EVENT_SCHEMAS["/nav/cycle"]
    pose_schema = codec.message_schema(PoseEstimate)
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(PROFILE, LIBRARY)
        ids = {s.name: writer.register_schema(s.name, s.encoding, s.data) for s in (cycle_schema, pose_schema)}
        channels = {f"/{side}/nav/{what}": writer.register_channel(
            f"/{side}/nav/{what}", codec.MESSAGE_ENCODING, ids[(cycle_schema if what == "cycle" else pose_schema).name])
            for side in ("recorded", "replayed") for what in ("cycle", "pose")}
        for side, cycles in (("recorded", result.recorded), ("replayed", result.replayed)):
            for cycle in cycles:
                ns = max(0, int(round(cycle.now * 1e9)))
                doc = {"now": codec.exact(cycle.now), "estimates": [codec.encode_estimate(e) for e in cycle.estimates],
                       "selected": cycle.selected}
                writer.add_message(channels[f"/{side}/nav/cycle"], log_time=ns, data=codec.dumps(doc), publish_time=ns)
                pose = next((e for e in cycle.estimates if isinstance(e, PoseEstimate) and e.source == cycle.selected), None)
                if pose is not None:
                    writer.add_message(channels[f"/{side}/nav/pose"], log_time=ns,
                                       data=codec.dumps(codec.encode_message(pose)), publish_time=ns)
        writer.finish()


def compare(result: ReplayResult, sources: set[str]) -> None:
    """Fill ``result``'s differences: cycle by cycle, the replayed estimates against the recorded
    ones of the replayed pipelines (an estimate's ``source`` is its pipeline's name, or starts with
    it and a dot)."""
    position: list[float] = []
    yaw: list[float] = []
    distance: list[float] = []
    for rec, rep in zip(result.recorded, result.replayed):
        mine = [e for e in rec.estimates if e.source.split(".")[0] in sources]
        same = len(mine) == len(rep.estimates) and rec.selected == rep.selected and all(
            codec.encode_estimate(a) == codec.encode_estimate(b) for a, b in zip(mine, rep.estimates))
        for a, b in zip(mine, rep.estimates):
            if type(a) is not type(b) or a.source != b.source:
                same = False
            elif isinstance(a, PoseEstimate):
                position.append(float(np.linalg.norm(a.position_ned - b.position_ned)))
                yaw.append(_angle_diff_deg(a.euler_rad[2], b.euler_rad[2]))
            elif isinstance(a, AttitudeEstimate):
                yaw.append(_angle_diff_deg(a.euler_rad[2], b.euler_rad[2]))
            elif isinstance(a, RangeEstimate):
                distance.append(abs(a.distance_m - b.distance_m))
        if not same:
            result.mismatched_cycles += 1
            if result.first_mismatch_t is None:
                result.first_mismatch_t = rec.now
    result.mismatched_cycles += abs(len(result.recorded) - len(result.replayed))
    result.max_position_diff_m = _max(position)
    result.max_yaw_diff_deg = _max(yaw)
    result.max_range_diff_m = _max(distance)


def _angle_diff_deg(a: float, b: float) -> float:
    """|a - b| wrapped to [0, 180] deg; 0 where both are NaN (an angle neither could observe),
    inf where only one is."""
    if math.isnan(a) and math.isnan(b):
        return 0.0
    if math.isnan(a) or math.isnan(b):
        return math.inf
    return abs(math.degrees(math.remainder(a - b, math.tau)))


def _max(values: list[float]) -> float | None:
    return max(values) if values else None


class Pacer:
    """Sleeps so that recorded time advances at ``speed`` times wall time (None: no pacing)."""

    def __init__(self, speed: float | None, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if speed is not None and not speed > 0:
            raise ValueError(f"--speed must be > 0, got {speed}")
        self.speed = speed
        self.clock = clock
        self.sleep = sleep
        self.start: tuple[float, float] | None = None  # (recorded t, wall t) of the first message

    def wait_for(self, t: float) -> None:
        """Return when recorded time ``t`` (s) is due."""
        if self.speed is None:
            return
        if self.start is None:
            self.start = (t, self.clock())
            return
        delay = self.start[1] + (t - self.start[0]) / self.speed - self.clock()
        if delay > 0:
            self.sleep(delay)
