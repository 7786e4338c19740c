"""Helpers for the tests against real ArduPilot SITL binaries in ../shared/ardupilot.

Every such test is marked :data:`requires_ardupilot` and skips cleanly when the binary is absent
(the binaries are not part of this repository). Each SITL runs on a free instance (ports
5760 + 10 x instance) in its own working directory.
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest
import yaml

from tests.conftest import REPO, free_port

ARDUPILOT_DIR = REPO.parent / "shared" / "ardupilot"
ARDUCOPTER = ARDUPILOT_DIR / "arducopter"
requires_ardupilot = pytest.mark.skipif(not os.access(ARDUCOPTER, os.X_OK),
                                        reason=f"no ArduPilot SITL binary at {ARDUCOPTER}")


def write_ardupilot_config(directory: Path, *, mission: str | None = None) -> Path:
    """config/sitl.yaml with free zenoh and GCS ports, absolute paths, the ArduCopter binary as the
    vehicle and config/missions beside it (``--mission NAME`` finds them there)."""
    raw = yaml.safe_load((REPO / "config" / "sitl.yaml").read_text())
    raw["telemetry"]["listen"] = [f"tcp/127.0.0.1:{free_port(socket.SOCK_STREAM)}"]
    raw["sitl"]["gcs_urls"] = [f"udpout:127.0.0.1:{free_port()}"]
    raw["sitl"]["vehicle_url"] = f"udpin:127.0.0.1:{free_port()}"
    raw["sitl"]["world"] = str(REPO / "config" / "worlds" / "arena.yaml")
    raw["pipelines"]["lidar"]["map"] = str(REPO / "config" / "worlds" / "arena.yaml")
    raw["sitl"]["ardupilot"] = {"binary": str(ARDUCOPTER)}
    raw["mission"]["file"] = str(REPO / "config" / "missions" / f"{mission}.yaml") if mission else None
    missions = directory / "missions"
    if not missions.exists():
        missions.symlink_to(REPO / "config" / "missions")
    path = directory / "companion.yaml"
    path.write_text(yaml.safe_dump(raw, sort_keys=False))
    return path
