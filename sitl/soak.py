"""`companion experiment soak --seconds 3600 --out R.json`: a long real-time flight that watches
the daemon's memory and rates (not in CI: it takes the time it says).

The flight is the config's mission ``soak`` (config/missions/soak.yaml: take off, hold, land) on
a :class:`sitl.rig.Rig` (the real Hokuyo driver behind the SCIP bridge, real time), its hold
rewritten to last ``--seconds`` + :data:`HOLD_MARGIN_S` (chained hold steps beyond the 3600 s
one step may hold), written to the work directory. Every :data:`SAMPLE_PERIOD_S` it records the
daemon's resident memory (its own ``system`` telemetry), the VISION_POSITION_ESTIMATE rate
reaching the autopilot (counted by the proxy, outside the daemon), the autopilot messages the
daemon received per second and the nav-loop jitter. The report compares the end of the run with
the end of the warm-up (:data:`WARM_UP_S`): RSS growth (MB) and rates then and now.

The report is written however the run ends (SIGTERM and SIGINT included): ``"completed": false``
and the samples so far if it did not last ``--seconds``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import tempfile
import time
from pathlib import Path

import yaml

from companion.config import Config, load_config
from sitl.rig import Rig, sigterm_exits, wait_until

log = logging.getLogger("companion.soak")

SAMPLE_PERIOD_S = 10.0
WARM_UP_S = 300.0
AIRBORNE_TIMEOUT_S = 90.0
HOLD_MARGIN_S = 3 * SAMPLE_PERIOD_S  # the hold outlasts the samples: the last one is still in it
HOLD_STEP_MAX_S = 3600.0  # a mission's hold step holds at most this (the mission schema)


def soak_mission(cfg: Config, seconds: float, out: Path) -> Path:
    """The config's ``missions/soak.yaml`` with its hold lasting ``seconds`` (several hold steps
    if need be), written to ``out``."""
    template = cfg.resolve("missions/soak.yaml")
    mission = yaml.safe_load(template.read_text())
    steps: list[dict] = []
    holds = 0
    for step in mission["steps"]:
        if "hold" not in step:
            steps.append(step)
            continue
        holds += 1
        chunks = max(1, math.ceil(seconds / HOLD_STEP_MAX_S))
        steps += [{"hold": {**step["hold"], "seconds": round(seconds / chunks, 3)}} for _ in range(chunks)]
    if holds != 1:
        raise ValueError(f"{template}: {holds} hold steps (the soak stretches exactly one)")
    mission["steps"] = steps
    out.write_text(yaml.safe_dump(mission, sort_keys=False))
    return out


def sample(rig: Rig, t: float, previous: dict | None) -> dict:
    """One row: time (s since the hold began), RSS (MB), estimate and received-message rates (Hz)
    over the last period, nav-loop jitter p99 (ms), mission state."""
    telemetry = rig.listener.snapshot()  # type: ignore[union-attr]
    system, link = telemetry.get("system", {}), telemetry.get("link", {})
    since = time.monotonic() - SAMPLE_PERIOD_S
    with rig.proxy.lock:
        estimates = sum(1 for e in rig.proxy.counters.estimates if e > since)
    received = link.get("messages_rx", 0)
    rx_hz = None if previous is None else (received - previous["messages_rx"]) / (t - previous["t"])
    return {"t": round(t, 1), "rss_mb": system.get("rss_mb"), "estimate_hz": estimates / SAMPLE_PERIOD_S,
            "messages_rx": received, "rx_hz": rx_hz,
            "loop_jitter_ms_p99": (system.get("loop_jitter_ms") or {}).get("p99"),
            "mission": telemetry.get("mission", {}).get("state")}


def summary(rows: list[dict]) -> dict:
    """The report's figures from the samples (see the module docstring); None where there are none."""
    if not rows:
        return {"seconds": 0.0, "warm_up_s": WARM_UP_S, "rss_mb_after_warm_up": None, "rss_mb_end": None,
                "rss_growth_mb": None, "estimate_hz_after_warm_up": None, "estimate_hz_end": None,
                "rx_hz_after_warm_up": None, "rx_hz_end": None, "mission_end": None}
    warm = [r for r in rows if r["t"] >= WARM_UP_S] or rows[-1:]
    first, last = warm[0], rows[-1]

    def mean(key: str, part: list[dict]) -> float | None:
        values = [r[key] for r in part if r[key] is not None]
        return sum(values) / len(values) if values else None

    early = [r for r in warm if r["t"] < first["t"] + WARM_UP_S]
    late = [r for r in rows if r["t"] > last["t"] - WARM_UP_S]
    return {"seconds": last["t"], "warm_up_s": WARM_UP_S,
            "rss_mb_after_warm_up": first["rss_mb"], "rss_mb_end": last["rss_mb"],
            "rss_growth_mb": None if first["rss_mb"] is None or last["rss_mb"] is None
            else round(last["rss_mb"] - first["rss_mb"], 2),
            "estimate_hz_after_warm_up": mean("estimate_hz", early), "estimate_hz_end": mean("estimate_hz", late),
            "rx_hz_after_warm_up": mean("rx_hz", early), "rx_hz_end": mean("rx_hz", late),
            "mission_end": last["mission"]}


def run_soak(args: argparse.Namespace) -> int:
    """The soak; writes ``args.out`` however it ends. Exit 0 if it lasted ``args.seconds``."""
    cfg = load_config(args.config)
    work = Path(tempfile.mkdtemp(prefix="companion-soak-"))
    rows: list[dict] = []
    completed = False
    error: str | None = None
    try:
        with sigterm_exits():
            mission = soak_mission(cfg, args.seconds + HOLD_MARGIN_S, work / "soak-mission.yaml")
            rig = Rig(cfg, mission, work, args.seed, status_period_s=1.0)  # the deployed status rate
            try:
                rig.start()
                if not wait_until(lambda: rig.telemetry("mission").get("step_kind") == "hold", AIRBORNE_TIMEOUT_S):
                    raise RuntimeError("the vehicle did not reach the hold step")
                started = time.monotonic()
                while (t := time.monotonic() - started) < args.seconds:
                    rows.append(sample(rig, t, rows[-1] if rows else None))
                    log.info("soak: %s", rows[-1])
                    if rig.daemon is None or rig.daemon.poll() is not None:
                        raise RuntimeError("the daemon exited during the soak")
                    time.sleep(SAMPLE_PERIOD_S)
                completed = True
            finally:
                rig.close()
    except RuntimeError as exc:
        error = str(exc)
        log.error("soak: %s", exc)
    finally:
        report = {"soak": summary(rows), "completed": completed, "error": error, "work_dir": str(work),
                  "samples": rows}
        Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps({**report["soak"], "completed": completed, "error": error}, indent=2))
    return 0 if completed else 1
