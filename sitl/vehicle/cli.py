"""The simulated vehicle's command line: ``python -m sitl.vehicle`` (see sitl/vehicle/__init__.py)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from companion.mavlink.link import load_signing_key
from sitl.vehicle.core import DEFAULT_HOME, Vehicle, VehicleConfig
from sitl.vehicle.receiving import finite


def _floats(count: int) -> Callable[[str], tuple[float, ...]]:
    """argparse type: ``count`` comma-separated floats."""

    def parse(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers") from None
        if len(values) != count or not finite(values):
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated finite numbers")
        return values

    return parse


def parse_args(argv: Sequence[str] | None = None) -> VehicleConfig:
    """The command line as a :class:`VehicleConfig`."""
    description = sys.modules[__package__].__doc__.split("\n", 1)[0]  # the package docstring's first line
    p = argparse.ArgumentParser(prog="python -m sitl.vehicle", description=description)
    p.add_argument("--companion", required=True, help="pymavlink URL of the companion link, e.g. udpin:127.0.0.1:14555")
    p.add_argument("--gcs", action="append", default=[], help="pymavlink URL of a ground-station link (repeatable)")
    p.add_argument("--lockstep", action="store_true", help="drive the companion's clock with TIMESYNC ticks")
    p.add_argument("--tick", type=float, default=0.005, help="simulation tick, s (default 0.005)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=None, help="simulation seconds to run, then exit 0")
    p.add_argument("--log", default=None, help="flight log JSON written at exit")
    p.add_argument("--home", type=_floats(3), default=DEFAULT_HOME, help="arena anchor LAT,LON,ALT (deg, deg, m AMSL)")
    p.add_argument("--no-gps", action="store_true", help="no GPS receiver")
    p.add_argument("--position-source", choices=("extnav", "gps"), default="extnav")
    p.add_argument("--wind", type=_floats(3), default=None, help="mean wind N,E,D (m/s)")
    p.add_argument("--gust", type=float, default=None, help="gust standard deviation (m/s)")
    p.add_argument("--start", type=_floats(3), default=(0.0, 0.0, 0.0), help="start pose N,E,YAW_DEG (m, m, deg)")
    p.add_argument("--sysid", type=int, default=1)
    p.add_argument("--vehicle", choices=("copter", "plane"), default="copter",
                   help="airframe and autopilot: ArduCopter-like quadrotor or ArduPlane-like fixed wing (on a runway "
                        "at --start, taking off along its heading)")
    p.add_argument("--in-flight", type=_floats(2), default=None, metavar="HEIGHT,AIRSPEED",
                   help="--vehicle plane only: start in level flight HEIGHT m above home at AIRSPEED m/s along the "
                        "--start heading, armed, in GUIDED circling the start point")
    p.add_argument("--event", type=_floats(5), action="append", default=[],
                   metavar="START,END,SIDESLIP_DEG_S,TILT_ROLL_DEG,TILT_PITCH_DEG",
                   help="from START to END simulation seconds: a yaw rate added to the turn coordination (--vehicle "
                        "plane: uncoordinated flight) and the autopilot's attitude estimate tilted by roll and pitch "
                        "(a fault it flies on) (repeatable)")
    p.add_argument("--refuse-interval", type=int, action="append", default=[], metavar="MSGID",
                   help="answer SET_MESSAGE_INTERVAL for this message id with MAV_RESULT_FAILED, as ArduPilot 4.0 does "
                        "for HIGHRES_IMU (105) and SIM_STATE (108) (repeatable)")
    p.add_argument("--legacy-streams", action="store_true",
                   help="answer SET_MESSAGE_INTERVAL with MAV_RESULT_UNSUPPORTED, as firmware that only knows "
                        "REQUEST_DATA_STREAM groups does")
    p.add_argument("--signing-key", metavar="FILE", default=None,
                   help="MAVLink 2 signing on the companion link with this key (32 raw bytes or 64 hex characters)")
    a = p.parse_args(argv)
    if a.in_flight is not None and a.vehicle != "plane":
        p.error("--in-flight needs --vehicle plane")
    if any(e[2] for e in a.event) and a.vehicle != "plane":
        p.error("an --event sideslip needs --vehicle plane")
    if a.tick <= 0 or (a.seconds is not None and a.seconds < 0) or not 1 <= a.sysid <= 255:
        p.error("--tick must be > 0, --seconds >= 0 and --sysid 1..255")
    try:
        key = load_signing_key(Path(a.signing_key)) if a.signing_key else None
    except (OSError, ValueError) as exc:
        p.error(f"--signing-key: {exc}")
    return VehicleConfig(
        companion=a.companion, gcs=tuple(a.gcs), lockstep=a.lockstep, tick_s=a.tick, seed=a.seed,
        seconds=a.seconds, log=a.log, home=a.home, gps=not a.no_gps, position_source=a.position_source,
        wind_ned_mps=a.wind, gust_mps=a.gust, start=a.start, sysid=a.sysid, legacy_streams=a.legacy_streams,
        refuse_intervals=tuple(a.refuse_interval), signing_key=key, airframe=a.vehicle,
        in_flight=a.in_flight, events=tuple(a.event))


@contextmanager
def _stop_on_signals(vehicle: Vehicle) -> Iterator[None]:
    """SIGTERM/SIGINT end the run cleanly (main thread only; elsewhere signals are left alone)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    for sig in previous:
        signal.signal(sig, lambda _signum, _frame: vehicle.request_stop())
    previous_wakeup = signal.set_wakeup_fd(vehicle.wake_fd, warn_on_full_buffer=False)
    try:
        yield
    finally:
        signal.set_wakeup_fd(previous_wakeup)
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the simulated vehicle; returns the exit status (0, or 3 for a lockstep timeout)."""
    vehicle = Vehicle(parse_args(argv))
    try:
        with _stop_on_signals(vehicle):
            return vehicle.run()
    finally:
        vehicle.close()
