"""The companion against the real ArduCopter 4.0 SITL (../shared/ardupilot; skipped without it).

The contract commands of the ArduPilot issue, run as a user runs them, scored against the SITL's
own truth with the built-in vehicle's report schema, and faults of the real firmware process.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.config import load_config
from sitl.ardupilot_run import ArduPilotRun
from sitl.harness import write_run_config
from tests.ardupilot_helpers import ARDUCOPTER, requires_ardupilot, write_ardupilot_config
from tests.conftest import REPO
from tests.sitl_helpers import wait_for
from tests.test_sitl_report import SCHEMA_1

pytestmark = requires_ardupilot


def companion_sitl(config: Path, report: Path, *args: str, timeout_s: float) -> tuple[dict, dict]:
    """`companion sitl --ardupilot PATH ... --report FILE`: (report, flight log)."""
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "sitl", "-c", str(config), "--ardupilot",
                           str(ARDUCOPTER), *args, "--report", str(report)],
                          cwd=REPO, capture_output=True, text=True, timeout=timeout_s)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
    flight_log = re.search(r"flight log \(truth, everything the autopilot received\) in (\S+)", proc.stdout)
    assert flight_log is not None, proc.stdout[-2000:]
    return json.loads(report.read_text()), json.loads(Path(flight_log.group(1)).read_text())


def assert_same_schema_as_the_built_in_vehicle(report: dict) -> None:
    assert set(report) == set(SCHEMA_1)
    for section, keys in SCHEMA_1.items():
        if keys is not None:
            assert set(report[section]) == keys, section


def assert_clean_autopilot(report: dict) -> None:
    autopilot = report["autopilot"]
    assert autopilot["firmware"] == "ArduPilot copter 4.0.5-rc"
    assert autopilot["internal_errors"] == []
    assert autopilot["nonfinite_dropped"] == 0
    assert autopilot["origin_confirmed"] and autopilot["external_nav_in_use"]


def test_hover_on_the_lidar_estimate_alone_arms_takes_off_holds_and_lands(tmp_path: Path) -> None:
    report, log = companion_sitl(write_ardupilot_config(tmp_path), tmp_path / "r.json",
                                 "--mission", "hover", "--seconds", "30", timeout_s=150)

    assert_same_schema_as_the_built_in_vehicle(report)
    assert_clean_autopilot(report)
    assert report["autopilot"]["vision_position_estimate_hz"] >= 25.0
    assert report["estimate"]["position_rms_m"] <= 0.05
    assert report["control"]["mission_completed"] and report["control"]["failsafes_triggered"] == []
    modes = [(mode, armed) for _, mode, armed in log["modes"]]
    assert ("GUIDED", True) in modes and modes[-1] == ("LAND", False)
    height = -np.asarray(log["truth"]["pos_ned"], dtype=float)[:, 2]
    assert height.max() == pytest.approx(1.0, abs=0.2)  # took off to 1 m (truth)
    assert height[-1] < 0.2  # and is back on the floor


def test_patrol_completes_with_tracking_within_15_cm_of_truth(tmp_path: Path) -> None:
    report, _ = companion_sitl(write_ardupilot_config(tmp_path), tmp_path / "r.json", "--mission", "patrol",
                               timeout_s=420)

    assert_same_schema_as_the_built_in_vehicle(report)
    assert_clean_autopilot(report)
    assert report["control"]["mission_completed"]
    assert report["control"]["tracking_rms_m"] <= 0.15
    assert report["control"]["failsafes_triggered"] == []
    assert report["estimate"]["position_rms_m"] <= 0.05


RECOVERY_S = 2.0  # origin re-sent and streams re-requested this soon after the autopilot answers again


def first_stream_request_after(run: ArduPilotRun, t: float) -> float | None:
    return next((at for at, _ in run.observer.tap.stream_requests if at >= t), None)


def assert_recovered(run: ArduPilotRun, since: float, what: str) -> float:
    """After ``since``: the autopilot answered (a HEARTBEAT to the companion), then the companion
    re-sent the origin and re-requested its streams within RECOVERY_S of that. Returns when it answered."""
    tap = run.observer.tap
    answered = wait_for(lambda: tap.first_after("to_companion:HEARTBEAT", since), 30, f"{what}: a heartbeat")
    origin = wait_for(lambda: tap.first_after("to_autopilot:SET_GPS_GLOBAL_ORIGIN", answered), 10,
                      f"{what}: the origin re-sent")
    streams = wait_for(lambda: first_stream_request_after(run, answered), 10, f"{what}: streams re-requested")
    assert origin - answered <= RECOVERY_S and streams - answered <= RECOVERY_S, (what, answered, origin, streams)
    return answered


def test_the_companion_recovers_when_the_autopilot_hangs_and_when_it_restarts(tmp_path: Path) -> None:
    config = write_ardupilot_config(tmp_path)
    cfg = load_config(config)
    run = ArduPilotRun(ARDUCOPTER, cfg.sitl.ardupilot, cfg.base_dir, tmp_path, seed=0)
    run_cfg = write_run_config(cfg, None, tmp_path, run.start_tap(), origin_at_takeoff=True)
    daemon: subprocess.Popen | None = None
    try:
        run.boot(run_cfg)
        run.begin()
        with open(tmp_path / "daemon.out", "w") as out:
            daemon = subprocess.Popen([sys.executable, "-m", "companion.cli", "run", "-c", str(run_cfg)], cwd=REPO,
                                      stdout=out, stderr=subprocess.STDOUT)
        state = run.observer.state
        assert state is not None
        wait_for(lambda: state.external_nav_in_use, 40, "the EKF using the companion's estimate")

        run.sitl.pause()  # hung: the connection stays, nothing is answered
        time.sleep(10.0)
        resumed = run.observer.now()
        run.sitl.resume()
        assert_recovered(run, resumed, "stopped for 10 s")

        run.sitl.kill()  # crashed, then started again with the parameters it had
        time.sleep(2.0)
        restarted = run.observer.now()
        run.sitl.start()
        assert run.sitl.wait_listening()
        listening = run.observer.now()
        answered = assert_recovered(run, restarted, "killed and restarted")
        # the companion dialled again within its longest reopen wait (2 s) of the port being back
        assert answered - listening <= 2.5, (listening, answered)
        wait_for(lambda: any(t >= restarted and "using external nav" in text for t, _, text in run.observer.log.statustext),
                 40, "the restarted EKF using the companion's estimate")
        assert run.alive  # and it is still running (a halt would have ended it: SITL_PANIC_EXIT)
    finally:
        rc, stop_s = None, None
        if daemon is not None:
            stopping = time.monotonic()
            daemon.send_signal(signal.SIGTERM)
            try:
                rc = daemon.wait(10)
            except subprocess.TimeoutExpired:  # rc stays None: reported below, after SITL is stopped too
                daemon.kill()
                daemon.wait()
            stop_s = time.monotonic() - stopping
        sitl_rc = run.stop()
    assert rc == 0 and stop_s <= 2.0, (rc, stop_s, (tmp_path / "daemon.out").read_text()[-3000:])
    assert sitl_rc == 0 and run.internal_errors() == []  # it ended on SIGTERM, not on an internal error
    assert run.observer.tap.nonfinite == 0
