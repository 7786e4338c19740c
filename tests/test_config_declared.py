"""config/sitl-declared.yaml and config/sitl-corridor-declared.yaml are config/sitl.yaml and
config/sitl-corridor.yaml with the built-in vehicle's and the clean world's noise declared to the
lidar pipeline, and nothing else: a change to a base config that its declared copy misses fails here."""

from __future__ import annotations

import pytest
import yaml

from tests.conftest import REPO

DECLARED_KEYS = {"survey_error_m", "accel_noise_density", "fix_time_sd_s", "line_model_error_m",
                 "corner_error_per_m", "heading_error_deg", "height_model_error_m",
                 "floor_tilt_error_deg", "mixed_pixels"}


@pytest.mark.parametrize(("declared", "base"), [("sitl-declared.yaml", "sitl.yaml"),
                                                ("sitl-corridor-declared.yaml", "sitl-corridor.yaml")])
def test_a_declared_config_is_its_base_but_for_the_lidar_noise_settings(declared: str, base: str) -> None:
    copy = yaml.safe_load((REPO / "config" / declared).read_text())
    original = yaml.safe_load((REPO / "config" / base).read_text())
    lidar = copy["pipelines"]["lidar"]
    assert DECLARED_KEYS <= lidar.keys() and not DECLARED_KEYS & original["pipelines"]["lidar"].keys()
    for key in DECLARED_KEYS:
        del lidar[key]
    assert copy == original
