"""`companion experiment soak --seconds 3600 --out R.json`: a long real-time flight that watches
the daemon's memory and rates (not in CI: it takes the time it says).

The flight is mission ``soak`` (take off, hold for an hour, land) on a :class:`sitl.rig.Rig`
(the real Hokuyo driver behind the SCIP bridge, real time). Every :data:`SAMPLE_PERIOD_S` it
records the daemon's resident memory (its own ``system`` telemetry), the VISION_POSITION_ESTIMATE
rate reaching the autopilot (counted by the proxy, outside the daemon), the autopilot messages
the daemon received per second and the nav-loop jitter. The report compares the end of the run
with the end of the warm-up (:data:`WARM_UP_S`): RSS growth (MB) and rates then and now.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

from companion.config import load_config
from sitl.rig import Rig, wait_until

log = logging.getLogger("companion.soak")

SAMPLE_PERIOD_S = 10.0
WARM_UP_S = 300.0
AIRBORNE_TIMEOUT_S = 90.0


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
    """The report's figures from the samples (see the module docstring)."""
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
    cfg = load_config(args.config)
    work = Path(tempfile.mkdtemp(prefix="companion-soak-"))
    rig = Rig(cfg, "soak", work, args.seed, status_period_s=1.0)  # the deployed status rate
    rows: list[dict] = []
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
    finally:
        rig.close()
    report = {"soak": summary(rows), "samples": rows}
    Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report["soak"], indent=2))
    return 0
