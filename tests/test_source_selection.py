"""Estimate-source selection: priority, failover on loss, hysteresis on return, commanded pin, one
reset per switch (companion/selection.py); a pipeline that gives no pose is never a source."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from companion.config import Config, ConfigError, ControlConfig, FailsafeConfig, PayloadConfig
from companion.daemon import Daemon, load_named_files
from companion.mission.context import MissionContext
from companion.mission.runner import MissionRunner
from companion.mission.steps import Mission
from companion.messages import PoseEstimate
from companion.plugins import register_pipeline
from companion.schema import SchemaError, load_text
from companion.selection import SourceSelector

PERIOD = 0.02  # a 50 Hz nav loop


def pose(source: str, t: float, north: float = 0.0, reset: bool = False, sigma_m: float = 0.01,
         degraded: bool = False) -> PoseEstimate:
    return PoseEstimate(t, np.array([north, 0.0, -1.0]), (0.0, 0.0, 0.0), np.eye(6) * sigma_m ** 2, reset=reset,
                        source=source, degraded=degraded)


class Run:
    """A selector driven cycle by cycle; records what it forwards and its switches."""

    def __init__(self, priority: list[str], timeout_s: float = 0.3, return_s: float = 2.0) -> None:
        self.switches: list[tuple[str | None, str | None, str]] = []
        self.selector = SourceSelector(priority, timeout_s, return_s, max_sigma_m=0.5,
                                       on_switch=lambda old, new, why: self.switches.append((old, new, why)))
        self.sigma_m: dict[str, float] = {}  # a source's position sigma in the poses it makes (default 0.01 m)
        self.coasting: set[str] = set()  # sources whose pipeline marks its poses degraded
        self.t = 0.0
        self.forwarded: list[PoseEstimate] = []

    def cycles(self, seconds: float, live: set[str]) -> None:
        """Run ``seconds`` of nav cycles in which the sources in ``live`` each make a pose."""
        for _ in range(round(seconds / PERIOD)):
            self.t += PERIOD
            new = {name: pose(name, self.t, north=10.0 if name == "b" else 0.0, sigma_m=self.sigma_m.get(name, 0.01),
                              degraded=name in self.coasting) for name in live}
            for estimate in new.values():
                self.selector.offer(estimate, self.t)
            chosen = self.selector.select(self.t, new)
            if chosen is not None:
                self.forwarded.append(chosen)

    def resets(self) -> int:
        return sum(e.reset for e in self.forwarded)


def test_the_first_source_in_priority_feeds_the_autopilot_alone() -> None:
    run = Run(["a", "b"])
    run.cycles(1.0, {"a", "b"})
    assert {e.source for e in run.forwarded} == {"a"} and len(run.forwarded) == 50
    assert run.resets() == 0 and run.switches == [(None, "a", "first estimate")]


def test_losing_the_primary_switches_to_the_secondary_with_exactly_one_reset() -> None:
    run = Run(["a", "b"])
    run.cycles(1.0, {"a", "b"})
    run.cycles(2.0, {"b"})  # a stops
    assert run.selector.active == "b" and run.switches[-1] == ("a", "b", "a lost")
    assert run.resets() == 1
    first_b = next(e for e in run.forwarded if e.source == "b")
    assert first_b.reset and first_b.t_capture == pytest.approx(1.0 + 0.3 + PERIOD, abs=PERIOD)  # after the timeout
    assert run.selector.current is not None and run.selector.current.source == "b"


def test_the_primary_takes_back_over_only_after_delivering_for_the_return_time() -> None:
    run = Run(["a", "b"], return_s=2.0)
    run.cycles(1.0, {"a", "b"})
    run.cycles(1.0, {"b"})
    run.cycles(1.0, {"a", "b"})  # a back, but not long enough
    assert run.selector.active == "b"
    run.cycles(1.1, {"a", "b"})
    assert run.selector.active == "a" and run.resets() == 2  # a -> b and b -> a, once each


def test_a_flapping_primary_does_not_make_the_estimate_jump_back_and_forth() -> None:
    run = Run(["a", "b"], return_s=2.0)
    run.cycles(1.0, {"b"})
    for _ in range(10):  # a delivers 1 s, drops 0.5 s, ...
        run.cycles(1.0, {"a", "b"})
        run.cycles(0.5, {"b"})
    assert {e.source for e in run.forwarded} == {"b"} and run.resets() == 0


def test_a_degraded_primary_hands_over_to_a_good_secondary_and_returns_once_good_again() -> None:
    run = Run(["a", "b"])
    run.cycles(1.0, {"a", "b"})
    run.sigma_m["a"] = 2.0  # coasting: still fresh, but its position sigma is beyond max_sigma_m (0.5 m)
    run.cycles(0.1, {"a", "b"})
    assert run.selector.active == "b" and run.switches[-1][2].startswith("a degraded")
    for _ in range(5):  # a flaps between good and degraded every 0.5 s: no switch back
        run.sigma_m["a"] = 0.01
        run.cycles(0.5, {"a", "b"})
        run.sigma_m["a"] = 2.0
        run.cycles(0.5, {"a", "b"})
    assert run.selector.active == "b"
    run.sigma_m["a"] = 0.01
    run.cycles(2.1, {"a", "b"})
    assert run.selector.active == "a" and run.resets() == 2


def test_a_coasting_primary_is_degraded_and_its_coasting_never_counts_towards_its_return() -> None:
    """As in flight: the lidar comes back for 1 s, then coasts (degraded, small sigma) before it is lost."""
    run = Run(["a", "b"])
    run.cycles(1.0, {"b"})
    run.cycles(1.0, {"a", "b"})  # good for 1 s
    run.coasting.add("a")
    run.cycles(0.7, {"a", "b"})  # coasting: fresh, but degraded by its pipeline
    assert run.selector.active == "b" and run.resets() == 0
    run.coasting.clear()
    run.cycles(1.0, {"a", "b"})
    run.coasting.add("a")  # the active source starts coasting: a good one takes over at once
    run.cycles(2.1, {"a", "b"})
    assert run.selector.active == "b"
    run.coasting.clear()
    run.cycles(2.1, {"a", "b"})
    assert run.selector.active == "a" and run.resets() == 1


def test_a_degraded_source_is_still_used_when_no_other_is_good() -> None:
    run = Run(["a", "b"])
    run.sigma_m.update(a=2.0, b=3.0)
    run.cycles(1.0, {"a", "b"})
    assert run.selector.active == "a" and len(run.forwarded) == 50


def test_no_source_forwards_nothing_and_the_same_source_coming_back_is_not_a_jump() -> None:
    run = Run(["a"])
    run.cycles(0.5, {"a"})
    run.cycles(1.0, set())
    assert run.selector.active is None and run.switches[-1][1] is None
    count = len(run.forwarded)
    run.cycles(0.5, {"a"})
    assert len(run.forwarded) > count and run.resets() == 0


def test_a_commanded_source_is_used_while_fresh_then_priority_resumes() -> None:
    run = Run(["a", "b"])
    run.cycles(0.5, {"a", "b"})
    run.selector.command("b")
    run.cycles(0.5, {"a", "b"})
    assert run.selector.active == "b" and run.switches[-1][2] == "commanded"
    run.cycles(0.5, {"a"})  # the pinned source is lost: back to priority order
    assert run.selector.active == "a" and run.resets() == 2
    with pytest.raises(ValueError):
        run.selector.command("c")


def test_a_non_finite_pose_does_not_keep_a_source_alive() -> None:
    run = Run(["a", "b"])
    run.cycles(0.5, {"a", "b"})
    for _ in range(30):
        run.t += PERIOD
        bad = PoseEstimate(run.t, np.array([np.nan, 0.0, 0.0]), (0.0, 0.0, 0.0), np.eye(6), source="a")
        good = pose("b", run.t)
        run.selector.offer(bad, run.t)
        run.selector.offer(good, run.t)
        run.selector.select(run.t, {"a": bad, "b": good})
    assert run.selector.active == "b"


@dataclass
class AttitudeOnlyConfig:
    """``pipelines.attitude_only``: a test pipeline that gives no pose."""

    def sensor_inputs(self) -> dict[str, str]:
        return {}


@register_pipeline("attitude_only", AttitudeOnlyConfig, poses=False)
def _attitude_only(section: AttitudeOnlyConfig, ctx: object) -> object:
    return object()


CONFIG = "origin: {lat: 1, lon: 2, alt: 3}\npipelines:\n  attitude_only: {}\n"


def test_a_pipeline_without_poses_is_no_source_and_missions_fly_on_the_autopilot() -> None:
    cfg = load_text(CONFIG, Config)
    assert list(cfg.pipelines.enabled) == ["attitude_only"] and cfg.source_priority() == []
    assert Daemon(cfg)._build_selector([object()]) is None  # type: ignore[list-item]


def test_a_pipeline_without_poses_cannot_be_listed_as_a_source() -> None:
    with pytest.raises(SchemaError, match=r"pipelines.sources\[0\]: 'attitude_only' is not an enabled pose pipeline"):
        load_text(CONFIG + "  sources: [attitude_only]\n", Config)


def two_source_run() -> Run:
    run = Run(["a", "b"])
    run.cycles(0.5, {"a", "b"})
    return run


def test_a_mission_step_commands_the_pose_source_and_hands_it_back() -> None:
    run = two_source_run()
    ctx = MissionContext(state=None, commander=None, setpoints=SimpleNamespace(), origin=None,  # type: ignore[arg-type]
                         estimate=lambda: None, nav_health=lambda: (None, ""), publish=lambda stream, payload: None,
                         control=ControlConfig(), failsafe=FailsafeConfig(), payload=PayloadConfig(), geofence=None,
                         select_source=run.selector.command)
    steps = load_text("name: m\nsteps:\n  - pose_source: {source: b}\n  - pose_source: {source: null}\n", Mission).steps
    runner = MissionRunner(Mission("m", steps), False, ctx, "land")
    asyncio.run(runner._run_step(steps[0]))
    run.cycles(0.2, {"a", "b"})
    assert run.selector.active == "b" and run.resets() == 1
    asyncio.run(runner._run_step(steps[1]))
    run.cycles(1.5, {"a", "b"})  # a has been delivering for source_return_s (2 s) by then
    assert run.selector.pinned is None and run.selector.active == "a" and run.resets() == 2


def test_a_mission_naming_a_source_the_config_lacks_is_refused_at_its_step(tmp_path: Path) -> None:
    mission = tmp_path / "m.yaml"
    mission.write_text("name: m\nsteps:\n  - pose_source: {source: attitude_only}\n")
    cfg = load_text(CONFIG + f"mission: {{file: {mission}}}\n", Config)
    with pytest.raises(ConfigError, match=r"mission.file: .*steps\[0\].pose_source.source: 'attitude_only' is not a pose source"):
        load_named_files(cfg)
