"""`companion experiment slam-recovery` (sitl/slam_experiment.py): the CLI runs the seed's three
simulations on a few seeds and writes the contract keys with plausible figures, all scored
against the simulator's truth."""

from __future__ import annotations

import json
import math
from pathlib import Path

from companion.cli import main

CONTRACT = ("sim1_final_rms_m", "sim2_base_error_m", "sim3_base_error_m", "sim3_nees_in_band_fraction",
            "baseline_sim3_base_error_m")


def test_slam_recovery_cli_writes_the_contract_keys_with_plausible_figures(tmp_path: Path, capsys) -> None:
    out = tmp_path / "r.json"
    assert main(["experiment", "slam-recovery", "--seeds", "2", "--seed", "3", "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    for key in CONTRACT:
        assert isinstance(report[key], float) and math.isfinite(report[key]), key
    assert report["seeds"] == [3, 4]
    assert report["sim1_final_rms_m"] < 1.0  # five loops around one landmark stay within a metre
    assert report["sim2_base_error_m"] > 3.0 * report["sim3_base_error_m"]  # dead reckoning is much worse
    assert report["sim3_base_error_m"] < 10.0
    assert report["baseline_sim3_base_error_m"] < 10.0
    assert 0.0 <= report["sim3_nees_in_band_fraction"] <= 1.0
    assert report["sim3_landed_fraction"] == 1.0
    # per loop, the map and the vehicle errors of simulation 1 do not grow after the first loop
    loops = report["sim1_vehicle_rms_per_loop_m"]
    assert len(loops) == 5 and loops[-1] <= loops[0] * 1.5
    assert len(report["per_seed"]) == 2
    printed = json.loads(capsys.readouterr().out)
    assert set(CONTRACT) <= set(printed)
