"""The fault suite as a user runs it: ``companion experiment faults --out R.json`` against the SITL
in real time (the real Hokuyo driver behind the SCIP bridge, the daemon's link behind the fault
proxy), on free loopback ports. Its contract fields, and the acceptance: every fault recovered,
no crash, no non-finite value sent to the autopilot, recovery within 2 s of the fault clearing,
and the patrol with a 3 s NaN / infinity storm completed with no failsafe.

The proxy and the bridge's fault commands are tested here through the suite; what each fault
means is in sitl/faults.py.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from sitl.faults import FLIGHT_FAULTS
from tests.conftest import REPO
from tests.sitl_helpers import real_driver_config

SUITE_TIMEOUT_S = 900
RECOVERY_BUDGET_S = 2.0
FIELDS = {"name", "recovered", "recovery_s", "crashes", "nonfinite_sent", "failsafes"}


def test_every_fault_of_the_suite_is_recovered_without_a_crash_or_a_nonfinite_value_sent(tmp_path: Path) -> None:
    config, _ = real_driver_config(tmp_path)
    out = tmp_path / "faults.json"
    proc = subprocess.run([sys.executable, "-m", "companion.cli", "experiment", "faults", "-c", str(config),
                           "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=SUITE_TIMEOUT_S)
    report = json.loads(out.read_text())
    table = proc.stdout[proc.stdout.find("| fault"):]
    faults = {f["name"]: f for f in report["faults"]}

    assert set(report) >= {"faults", "all_recovered"}
    assert all(set(f) >= FIELDS for f in report["faults"])
    assert set(faults) >= {f.name for f in FLIGHT_FAULTS} | {
        "patrol_nan_storm", "sigterm_before_autopilot", "sigterm_never_accepting_tcp_peer", "sigterm_in_flight",
        "sigterm_autopilot_stopped", "config_dev_zero", "config_fifo", "config_empty", "config_binary",
        "config_missing_mission"}
    assert report["all_recovered"] is True and proc.returncode == 0, table
    for name, fault in faults.items():
        assert fault["crashes"] == 0 and fault["nonfinite_sent"] == 0, (name, fault)
        assert fault["recovery_s"] is not None and fault["recovery_s"] <= RECOVERY_BUDGET_S, (name, fault)
    assert faults["patrol_nan_storm"]["failsafes"] == 0, faults["patrol_nan_storm"]
    assert faults["autopilot_killed_restarted"]["recovered"]  # counted as exactly one reboot
