"""The fault suite as a user runs it: ``companion experiment faults --out R.json`` against the SITL
in real time (the real Hokuyo driver behind the SCIP bridge, the daemon's link behind the fault
proxy), on free loopback ports. Its contract fields, and the acceptance: every fault recovered,
no crash, no non-finite value sent to the autopilot, recovery within 2 s of the fault clearing
(flight faults, the patrol storm, SIGTERM; a bad config file: the error within the suite's
CONFIG_BUDGET_S, Python's start-up included), and the patrol with a 3 s NaN / infinity storm
completed with no failsafe.

The suite runs in its own session: if it overruns, its whole process group (vehicle, bridge,
daemon, CPU hogs) is stopped and the test fails with what it printed.

The proxy and the bridge's fault commands are tested here through the suite; what each fault
means is in sitl/faults.py.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sitl.faults import CONFIG_BUDGET_S, CONFIG_FAULTS, FLIGHT_FAULTS
from tests.conftest import REPO
from tests.sitl_helpers import real_driver_config

SUITE_TIMEOUT_S = 900
TERM_GRACE_S = 20  # after SIGTERM, the suite stops its processes and writes its report
RECOVERY_BUDGET_S = 2.0
FIELDS = {"name", "recovered", "recovery_s", "crashes", "nonfinite_sent", "failsafes"}


def run_suite(args: list[str]) -> tuple[int, str, str]:
    """Run the suite in a new session: (exit status, stdout, stderr). On overrun, SIGTERM then
    SIGKILL its process group and fail with its output; fail too if it left a process running."""
    proc = subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=SUITE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=TERM_GRACE_S)
        except subprocess.TimeoutExpired:
            kill_group(proc.pid)
            out, err = proc.communicate()
        kill_group(proc.pid)  # whatever it left running
        pytest.fail(f"the fault suite overran {SUITE_TIMEOUT_S} s (exit {proc.returncode} once stopped)\n"
                    f"--- stdout ---\n{out[-20000:]}\n--- stderr ---\n{err[-20000:]}")
    if group_alive(proc.pid, wait_s=5.0):
        kill_group(proc.pid)
        pytest.fail(f"the fault suite exited ({proc.returncode}) leaving processes of its group running\n"
                    f"--- stderr ---\n{err[-20000:]}")
    return proc.returncode, out, err


def group_alive(pgid: int, wait_s: float = 0.0) -> bool:
    """Whether a process of group ``pgid`` is still running ``wait_s`` from now (at the latest)."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        if time.monotonic() >= deadline:
            return True
        time.sleep(0.1)


def kill_group(pgid: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(pgid, signal.SIGKILL)


def test_every_fault_of_the_suite_is_recovered_without_a_crash_or_a_nonfinite_value_sent(tmp_path: Path) -> None:
    config, _ = real_driver_config(tmp_path)
    out = tmp_path / "faults.json"
    rc, stdout, stderr = run_suite([sys.executable, "-m", "companion.cli", "experiment", "faults", "-c", str(config),
                                    "--out", str(out)])
    assert out.exists(), f"no report (exit {rc})\n--- stderr ---\n{stderr[-20000:]}"
    report = json.loads(out.read_text())
    table = stdout[stdout.find("| fault"):]
    faults = {f["name"]: f for f in report["faults"]}

    assert set(report) >= {"faults", "all_recovered"}
    assert all(set(f) >= FIELDS for f in report["faults"])
    assert set(faults) >= {f.name for f in FLIGHT_FAULTS} | {
        "patrol_nan_storm", "sigterm_before_autopilot", "sigterm_never_accepting_tcp_peer", "sigterm_in_flight",
        "sigterm_autopilot_stopped", "config_dev_zero", "config_fifo", "config_empty", "config_binary",
        "config_missing_mission"}
    assert report["all_recovered"] is True and rc == 0, table
    for name, fault in faults.items():
        budget = CONFIG_BUDGET_S if name in CONFIG_FAULTS else RECOVERY_BUDGET_S
        assert fault["crashes"] == 0 and fault["nonfinite_sent"] == 0, (name, fault)
        assert fault["recovery_s"] is not None and fault["recovery_s"] <= budget, (name, fault)
    assert faults["patrol_nan_storm"]["failsafes"] == 0, faults["patrol_nan_storm"]
