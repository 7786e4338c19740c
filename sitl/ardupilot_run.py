"""`companion sitl --ardupilot PATH`: a real ArduPilot SITL as the vehicle, set up by the companion.

One run: start the tap (sitl/ardupilot_observer.py), start SITL with wiped parameters at the
take-off pose of the run config (which the harness writes with the origin at the take-off point,
sitl/frame_shift.py: so SITL's home is the config origin), let ``companion setup-autopilot
--apply --reboot`` write what the companion needs for this config plus the harness's SITL
parameters (:data:`TRUTH_PARAMETERS`, ``sitl.ardupilot.parameters``) and reboot it, wait until it
is back, then record (the observer's ground link) while the daemon flies through the tap.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from companion.config import ArduPilotSitlConfig, OriginConfig, load_config
from sitl.ardupilot import ArduPilotSitl, SitlOptions, default_defaults, free_instance, home_at, serial_port
from sitl.ardupilot_observer import ArduPilotObserver
from sitl.frame_shift import takeoff_pose

# The SITL barometer is the truth altimeter of sitl/truth.py: none of its error sources.
TRUTH_PARAMETERS = {"SIM_BARO_RND": 0.0, "SIM_BARO_DRIFT": 0.0, "SIM_BARO_GLITCH": 0.0, "SIM_BARO_DELAY": 0.0,
                    "SIM_TEMP_BFACTOR": 0.0}
BOOT_S = 20.0  # SITL listening after a start or a reboot
SETUP_TIMEOUT_S = 60.0


class ArduPilotStartFailure(Exception):
    """SITL or its set-up did not come up; the message says which."""


class ArduPilotRun:
    """The ArduPilot side of one harness run (see the module docstring)."""

    def __init__(self, binary: Path, options: ArduPilotSitlConfig, base_dir: Path, work: Path, seed: int,
                 autopilot_sysid: int = 1) -> None:
        """``options``: the config's ``sitl.ardupilot`` (relative paths against ``base_dir``)."""
        self.binary = binary
        self.options = options
        self.base_dir = base_dir
        self.work = work
        self.instance = free_instance()
        self.observer = ArduPilotObserver(serial0_port=serial_port(self.instance, 0),
                                          serial1_port=serial_port(self.instance, 1), seed=seed,
                                          autopilot_sysid=autopilot_sysid,
                                          parameter_events=options.parameter_events)
        self.parameters = {**options.parameters, **TRUTH_PARAMETERS}
        self.sitl: ArduPilotSitl | None = None
        self.origin: OriginConfig | None = None

    def start_tap(self) -> str:
        """The daemon's MAVLink endpoint (the tap in front of SERIAL0)."""
        return f"tcp:127.0.0.1:{self.observer.start()}"

    def boot(self, run_config: Path) -> None:
        """Start SITL at the take-off pose of ``run_config`` with wiped parameters and set it up for
        that config (see the module docstring)."""
        cfg = load_config(run_config)
        start = takeoff_pose(cfg)
        self.origin = cfg.origin
        o = self.options
        defaults = (self.base_dir / o.defaults) if o.defaults else default_defaults(self.binary)
        home = home_at((cfg.origin.lat, cfg.origin.lon, cfg.origin.alt), start)
        self.sitl = sitl = ArduPilotSitl(SitlOptions(self.binary, o.model, defaults, home), self.work / "ardupilot",
                                         instance=self.instance)
        sitl.start(wipe=True)
        if not sitl.wait_listening(BOOT_S):
            raise ArduPilotStartFailure(f"ArduPilot SITL did not start (exit {sitl.returncode}; see {sitl.output})")
        cmd = [sys.executable, "-m", "companion.cli", "setup-autopilot", "-c", str(run_config),
               "--mavlink", sitl.url(2), "--apply", "--reboot", "--timeout", f"{SETUP_TIMEOUT_S:g}"]
        for name, value in sorted(self.parameters.items()):
            cmd += ["--param", f"{name}={value:g}"]
        try:
            rc = subprocess.run(cmd, timeout=SETUP_TIMEOUT_S * 2).returncode
        except subprocess.TimeoutExpired:
            rc = None
        if rc != 0:
            raise ArduPilotStartFailure(f"`companion setup-autopilot` against ArduPilot SITL failed (exit {rc})")
        if not sitl.wait_listening(BOOT_S):
            raise ArduPilotStartFailure(f"ArduPilot SITL did not come back after its reboot "
                                        f"(exit {sitl.returncode}; see {sitl.output})")

    def begin(self) -> None:
        """Time zero: record from now on."""
        assert self.origin is not None, "boot() first"
        self.observer.begin(self.origin)

    @property
    def alive(self) -> bool:
        return self.sitl is not None and self.sitl.running

    def internal_errors(self) -> list[str]:
        return self.sitl.internal_errors() if self.sitl is not None else []

    def stop(self) -> int | None:
        """Stop recording, then SITL (SIGTERM, SIGKILL on timeout); SITL's exit code."""
        self.observer.stop()
        return self.sitl.stop() if self.sitl is not None else None

    def write_log(self, path: Path) -> None:
        self.observer.write_log(path)
