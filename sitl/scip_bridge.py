"""Simulated Hokuyo scanners behind the real SCIP 2.0 driver: SITL truth -> rendered scans -> TCP.

::

    python -m sitl.scip_bridge --vehicle udpin:127.0.0.1:14560 --world config/worlds/arena.yaml \\
        --home 1.2966,103.7764,10.0 --seed 0 \\
        --sensor lidar_h,UTM-30LX,0,0,-0.10,0,0,0,10940 --sensor lidar_v,URG-04LX,0.05,0,-0.05,90,0,0,10941

The bridge is a ground station on an extra link of the SITL vehicle (start the vehicle with the
matching ``--gcs``, here ``udpout:127.0.0.1:14560``; ``companion sitl`` does it when
``sitl.scip_sensors`` names sensors). It asks the vehicle for ``SIM_STATE`` at 100 Hz
(SET_MESSAGE_INTERVAL, asked again whenever the stream stops for a second), converts every
sample to LOCAL_NED at ``--home`` (as sitl/truth.py does: the built-in vehicle's ATT_POS_MOCAP
refines the 1.1 cm steps of SIM_STATE's lat_int/lon_int) stamped with this process's monotonic
clock on arrival, and keeps two seconds of it. For every ``--sensor`` it serves a
:class:`sitl.scip_emulator.ScipEmulator` on TCP 127.0.0.1:PORT, so the daemon's *real* driver
(drivers/hokuyo.py, ``backend: real``, ``host: 127.0.0.1``) talks SCIP 2.0 to it exactly as to an
Ethernet scanner.

Scans are rendered like the ``sim`` backend's (sitl/lidar_sim.py: same world, model,
mount, range noise and dropout; sensor ``i`` draws its noise from seed ``--seed + i``), with one difference that the
real driver's timestamps make observable: a device measures its beams one after another while
the mirror turns, and the driver stamps beam ``k`` at step 0 + ``step_k`` step times. So every
beam is rendered from the pose at its own time (truth interpolated per beam: position
linearly, attitude by normalised quaternion interpolation), not the whole scan from one pose.

Time: the emulator's 24-bit millisecond clock is the asyncio loop clock, i.e. this process's
``time.monotonic()``, and truth is stamped with the same clock, so the sensor timestamp of a
scan and the poses it was rendered from agree to the millisecond the protocol carries. The
emulator asks for a scan when its sweep is over (step 0 + sweep); the scan is rendered for a
step 0 ``RENDER_LAG_S`` earlier still, so that every beam time is normally covered by
received truth (SIM_STATE every 10 ms) and interpolated, not extrapolated (a late sample is
bridged at constant velocity for up to ``MAX_EXTRAPOLATE_S``). To the driver this looks like
``RENDER_LAG_S`` of transfer latency: it maps the sensor clock through TM and learns the
delivery delay, so capture times stay exact. If no truth covers a scan (none yet, or the
stream stalled for more than ``MAX_EXTRAPOLATE_S``), the scanner sees nothing: every step
reports an error code, as a scanner with no returns does.

Real time only. The bridge runs on the wall clock (it cannot take part in lockstep: the SCIP
stream and the driver's clock sync are wall-clock protocols), so ``companion sitl --lockstep``
refuses ``sitl.scip_sensors``; deterministic runs use the in-daemon ``backend: sim``. The
bridge exists to exercise the real driver, its protocol handling, clock mapping and recovery,
end to end in SITL and tests.

With ``--faults-from-stdin`` the bridge also reads fault commands, one per line, from its
standard input (the fault suite, ``companion experiment faults``, drives it so):
``unplug NAME SECONDS``, ``corrupt NAME N``, ``garbage NAME N``, ``delay NAME N SECONDS``
(:class:`sitl.scip_emulator.ScipEmulator`'s faults on scanner NAME). A bad line is reported on
stderr and ignored.

It exits 0 on SIGTERM or SIGINT, after printing how many scans each scanner served.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import select
import signal
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Coroutine, Sequence
from dataclasses import dataclass

import numpy as np

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink picks its wire protocol

from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mav  # noqa: E402

from companion.config import MountConfig  # noqa: E402
from companion.schema import SchemaError  # noqa: E402
from drivers.lidar_models import MODELS as LIDAR_MODELS  # noqa: E402
from sitl.lidar_sim import SimLidarSettings, SimulatedLidar  # noqa: E402
from drivers.mount import Mount  # noqa: E402
from companion.messages import Scan  # noqa: E402
from sitl.scip_emulator import ScipEmulator  # noqa: E402
from sitl.truth import MocapRefinement, sim_state_position  # noqa: E402
from companion.world import World, load_world  # noqa: E402

SIM_STATE_HZ = 100.0
HISTORY_S = 2.0  # truth kept for interpolation
RENDER_LAG_S = 1.0 / SIM_STATE_HZ + 0.005  # a scan's last beam this long before it is sent: truth covers it
MAX_EXTRAPOLATE_S = 0.05  # a late truth stream is extrapolated (velocity, held attitude) this far, no further
TRUTH_TIMEOUT_S = 1.0  # no SIM_STATE for this long: ask for it again
REQUEST_RETRY_S = 0.5  # between two requests
RECEIVE_POLL_S = 0.1
BRIDGE_SYSID = 255  # a ground-station tool on a GCS link
BRIDGE_COMPID = mav.MAV_COMP_ID_USER1
AUTOPILOT_COMPID = mav.MAV_COMP_ID_AUTOPILOT1
NO_RETURN_MM = 1  # the value of a step without a return: an error code below every model's DMIN


# --- truth ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Pose:
    """A vehicle pose (what :class:`sitl.lidar_sim.SimulatedLidar` renders from)."""

    position_ned: np.ndarray  # (3,) m
    quat: np.ndarray  # (4,) [w, x, y, z], body FRD -> NED


class TruthHistory:
    """Simulator truth on this process's monotonic clock: ``HISTORY_S`` of samples, thread-safe
    (the MAVLink receiver thread adds, the event loop reads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._t: deque[float] = deque()
        self._rows: deque[np.ndarray] = deque()  # [n, e, d, vn, ve, vd, qw, qx, qy, qz]

    def add(self, t: float, position_ned: np.ndarray, velocity_ned: np.ndarray, quat: np.ndarray) -> None:
        q = np.asarray(quat, dtype=float)
        q = q / np.linalg.norm(q)
        row = np.concatenate((np.asarray(position_ned, float), np.asarray(velocity_ned, float), q))
        with self._lock:
            if self._t and t <= self._t[-1]:
                return  # keep the times strictly increasing
            self._t.append(t)
            self._rows.append(row)
            while t - self._t[0] > HISTORY_S:
                self._t.popleft()
                self._rows.popleft()

    @property
    def latest_t(self) -> float | None:
        with self._lock:
            return self._t[-1] if self._t else None

    def poses(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(positions (N, 3), unit quaternions (N, 4)) at the increasing ``times`` (s), or None
        if any lies before the history or more than ``MAX_EXTRAPOLATE_S`` after its newest sample."""
        with self._lock:
            if not self._t:
                return None
            ts = np.fromiter(self._t, float, len(self._t))
            rows = np.array(self._rows)
        times = np.asarray(times, dtype=float)
        if times[0] < ts[0] or times[-1] > ts[-1] + MAX_EXTRAPOLATE_S:
            return None
        if len(ts) == 1:
            b = a = np.zeros(len(times), dtype=int)
            w = np.zeros(len(times))
        else:
            b = np.clip(np.searchsorted(ts, times, side="right"), 1, len(ts) - 1)
            a = b - 1
            w = np.clip((times - ts[a]) / (ts[b] - ts[a]), 0.0, 1.0)
        position = rows[a, 0:3] + w[:, None] * (rows[b, 0:3] - rows[a, 0:3])
        qa, qb = rows[a, 6:10], rows[b, 6:10]
        qb = np.where(np.sum(qa * qb, axis=1, keepdims=True) < 0.0, -qb, qb)  # the short way round
        quat = (1.0 - w)[:, None] * qa + w[:, None] * qb
        quat /= np.linalg.norm(quat, axis=1, keepdims=True)
        late = times > ts[-1]  # past the newest sample: constant velocity, attitude held
        if np.any(late):
            position[late] = rows[-1, 0:3] + (times[late] - ts[-1])[:, None] * rows[-1, 3:6]
            quat[late] = rows[-1, 6:10]
        return position, quat

    def at(self, t: float) -> Pose | None:
        """The pose at ``t`` (the TruthLike protocol of sitl/truth.py)."""
        found = self.poses(np.array([t]))
        return None if found is None else Pose(found[0][0], found[1][0])


def rotations_from_quats(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices (body FRD -> NED) of unit quaternions (N, 4) [w, x, y, z];
    :func:`companion.frames.rotation_from_quat`, vectorised."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack((
        np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), axis=1),
        np.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), axis=1),
        np.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), axis=1),
    ), axis=1)


class VehicleTruth:
    """The MAVLink side: one GCS link to the SITL vehicle, read by a thread.

    Waits for the autopilot's HEARTBEAT (a ``udpin`` link answers the last sender), asks for
    SIM_STATE at ``SIM_STATE_HZ`` with SET_MESSAGE_INTERVAL, and asks again whenever no
    SIM_STATE arrived for ``TRUTH_TIMEOUT_S`` (a restarted vehicle forgets the request). Every
    sample goes into ``history`` stamped with ``time.monotonic()`` at reception.
    """

    def __init__(self, url: str, home: tuple[float, float, float], history: TruthHistory) -> None:
        self.url = url
        self.home = home
        self.history = history
        self.conn = mavutil.mavlink_connection(url, source_system=BRIDGE_SYSID, source_component=BRIDGE_COMPID,
                                               dialect="ardupilotmega")
        self.samples = 0
        self.requests = 0
        self._mocap = MocapRefinement()
        self._autopilot: tuple[int, int] | None = None
        self._last_sample: float | None = None
        self._last_request = -math.inf
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="mavlink", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.conn.close()

    def _run(self) -> None:
        while not self._stop.is_set():
            readable, _, _ = select.select([self.conn.fd], [], [], RECEIVE_POLL_S)
            if readable:
                while (msg := self.conn.recv_msg()) is not None:
                    self._handle(msg, time.monotonic())
            self._maybe_request(time.monotonic())

    def _handle(self, msg: mav.MAVLink_message, now: float) -> None:
        mtype = msg.get_type()
        if mtype == "ATT_POS_MOCAP":
            self._mocap.on_mocap(msg, now)
        elif mtype == "SIM_STATE":
            self.history.add(now, self._mocap.position(sim_state_position(msg, self.home), now),
                             np.array([msg.vn, msg.ve, msg.vd]), np.array([msg.q1, msg.q2, msg.q3, msg.q4]))
            if self._last_sample is None:
                print(f"sitl.scip_bridge: SIM_STATE truth flowing from {self.url}", flush=True)
            self._last_sample = now
            self.samples += 1
        elif (mtype == "HEARTBEAT" and msg.get_srcComponent() == AUTOPILOT_COMPID
              and msg.autopilot != mav.MAV_AUTOPILOT_INVALID):
            self._autopilot = (msg.get_srcSystem(), msg.get_srcComponent())

    def _maybe_request(self, now: float) -> None:
        if self._autopilot is None or now - self._last_request < REQUEST_RETRY_S:
            return
        if self._last_sample is not None and now - self._last_sample < TRUTH_TIMEOUT_S:
            return
        self.conn.mav.command_long_send(*self._autopilot, mav.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                        mav.MAVLINK_MSG_ID_SIM_STATE, 1e6 / SIM_STATE_HZ, 0, 0, 0, 0, 0)
        self._last_request = now
        self.requests += 1


# --- scanners ---------------------------------------------------------------------------------

class SweptLidar(SimulatedLidar):
    """:class:`sitl.lidar_sim.SimulatedLidar` (same world geometry, beams, mount, range noise
    and dropouts) rendering each beam from the vehicle pose at that beam's own time."""

    def render_sweep(self, beam_times: np.ndarray, positions: np.ndarray, quats: np.ndarray,
                     sequence: int = 0) -> Scan:
        """The scan of beams measured at ``beam_times`` (N,) from poses ``positions`` (N, 3)
        and ``quats`` (N, 4) (body FRD -> NED); stamped at its first beam, sweep included."""
        body_to_ned = rotations_from_quats(quats)
        origins = positions + body_to_ned @ self.mount.offset_m
        directions = np.einsum("nij,nj->ni", body_to_ned @ self.mount.rotation, self._directions)
        ranges, valid = self.measure(self.true_ranges(beam_times, origins, directions))
        return Scan(self.sensor_id, float(beam_times[0]), self._angles, ranges, valid,
                    sweep_s=float(beam_times[-1] - beam_times[0]), sequence=sequence)


@dataclass(frozen=True)
class SensorSpec:
    """One ``--sensor NAME,MODEL,X,Y,Z,ROLL,PITCH,YAW_DEG,PORT``."""

    name: str
    model: str
    mount: MountConfig
    port: int

    @classmethod
    def parse(cls, text: str) -> SensorSpec:
        parts = text.split(",")
        if len(parts) != 9:
            raise argparse.ArgumentTypeError("expected NAME,MODEL,X,Y,Z,ROLL,PITCH,YAW_DEG,PORT")
        name, model = parts[0], parts[1]
        if model not in LIDAR_MODELS:
            raise argparse.ArgumentTypeError(f"model {model!r}: one of {', '.join(sorted(LIDAR_MODELS))}")
        try:
            x, y, z, roll, pitch, yaw = (float(v) for v in parts[2:8])
            port = int(parts[8])
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r}: X..YAW_DEG must be numbers and PORT an integer") from None
        if not all(math.isfinite(v) for v in (x, y, z, roll, pitch, yaw)) or not 1 <= port <= 65535:
            raise argparse.ArgumentTypeError(f"{text!r}: finite mount values and a port 1..65535 expected")
        return cls(name, model, MountConfig((x, y, z), (roll, pitch, yaw)), port)


class BridgedScanner:
    """One emulated scanner: a :class:`ScipEmulator` whose scans are rendered from the truth."""

    def __init__(self, spec: SensorSpec, world: World, truth: TruthHistory, seed: int,
                 clock: Callable[[], float], noise_scale: float = 1.0) -> None:
        self.spec = spec
        self.params = params = LIDAR_MODELS[spec.model].pp
        self.truth = truth
        settings = SimLidarSettings(model=spec.model, seed=seed, noise_scale=noise_scale)  # type: ignore[arg-type]
        self.lidar = SweptLidar(spec.name, settings, Mount.from_config(spec.mount), world, truth)
        self.emulator = ScipEmulator(params, self._scan)
        self._clock = clock
        # Step k is measured k step times after step 0; the emulator sends a full scan once the
        # mirror has passed AMAX, (AMAX + 1) step times after step 0.
        self._step_offsets = np.arange(params.amin, params.amax + 1) * params.step_time_s
        self._sent_after_step0 = (params.amax + 1) * params.step_time_s
        self.port = spec.port  # the one listened on, once started (spec.port 0: any free port)
        self.rendered = 0
        self.blind = 0  # scans served without truth (no returns)
        self._stalled = False

    async def start(self) -> None:
        self.port = await self.emulator.start_tcp("127.0.0.1", self.spec.port)
        print(f"sitl.scip_bridge: {self.spec.name}: {self.spec.model} on tcp 127.0.0.1:{self.port}", flush=True)

    async def close(self) -> None:
        await self.emulator.close()

    def _scan(self) -> tuple[int, np.ndarray]:
        """The emulator's scan source: (sensor timestamp ms of step 0, ranges mm AMIN..AMAX)."""
        t_step0 = self._clock() - self._sent_after_step0 - RENDER_LAG_S
        stamp = self.emulator.clock_ms(t_step0)
        times = t_step0 + self._step_offsets
        poses = self.truth.poses(times)
        if poses is None:
            self.blind += 1
            latest = self.truth.latest_t
            if self.rendered and not self._stalled and latest is not None:  # (before the first truth: just early)
                print(f"sitl.scip_bridge: {self.spec.name}: SIM_STATE truth stopped {self._clock() - latest:.2f} s ago; "
                      "the scanner sees nothing until it is back", file=sys.stderr, flush=True)
            self._stalled = True
            return stamp, np.full(self.params.steps, NO_RETURN_MM, dtype=np.int64)
        self._stalled = False
        scan = self.lidar.render_sweep(times, *poses, sequence=self.rendered)
        self.rendered += 1
        mm = np.minimum(np.rint(scan.ranges_m * 1000.0), self.params.dmax_mm).astype(np.int64)
        return stamp, np.where(scan.valid, mm, NO_RETURN_MM)


# --- process ----------------------------------------------------------------------------------

async def serve(args: argparse.Namespace) -> int:
    loop = asyncio.get_running_loop()
    world = load_world(args.world)
    history = TruthHistory()
    # One clock for everything: the emulators' 24-bit clocks run on loop.time(), the truth is
    # stamped with time.monotonic(); asyncio's loop clock is time.monotonic().
    clock = loop.time
    if abs(clock() - time.monotonic()) > 0.01:
        raise RuntimeError("the event loop's clock is not time.monotonic()")
    scanners = [BridgedScanner(spec, world, history, (args.seed + i) % 1_000_000, clock)
                for i, spec in enumerate(args.sensor)]
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    vehicle = VehicleTruth(args.vehicle, args.home, history)
    try:
        for scanner in scanners:
            await scanner.start()
        vehicle.start()
        if args.faults_from_stdin:
            by_name = {s.spec.name: s.emulator for s in scanners}
            threading.Thread(target=_read_fault_commands, args=(loop, by_name), daemon=True).start()
        await stop.wait()
    finally:
        vehicle.stop()
        for scanner in scanners:
            await scanner.close()
    served = ", ".join(f"{s.spec.name} {s.rendered} scans ({s.blind} without truth)" for s in scanners)
    print(f"sitl.scip_bridge: stopped; {vehicle.samples} SIM_STATE samples; {served}", flush=True)
    return 0


def _read_fault_commands(loop: asyncio.AbstractEventLoop, emulators: dict[str, ScipEmulator]) -> None:
    """Thread: apply every fault command line of stdin (see the module docstring) on ``loop``."""
    for line in sys.stdin:
        try:
            fault = _fault_command(line.split(), emulators)
        except (ValueError, IndexError, KeyError) as exc:
            print(f"sitl.scip_bridge: bad fault command {line.strip()!r}: {exc}", file=sys.stderr, flush=True)
            continue
        loop.call_soon_threadsafe(fault)


_fault_tasks: set[asyncio.Task] = set()  # unplugs in progress: the loop keeps only weak references to tasks


def _start_task(coro: Coroutine[object, object, object]) -> None:
    """Run ``coro`` on the running loop, holding a reference until it is done."""
    task = asyncio.ensure_future(coro)
    _fault_tasks.add(task)
    task.add_done_callback(_fault_task_done)


def _fault_task_done(task: asyncio.Task) -> None:
    _fault_tasks.discard(task)
    if not task.cancelled() and task.exception() is not None:
        print(f"sitl.scip_bridge: fault command failed: {task.exception()!r}", file=sys.stderr, flush=True)


def _fault_command(words: list[str], emulators: dict[str, ScipEmulator]) -> Callable[[], object]:
    """The call applying one parsed fault command (run on the bridge's loop)."""
    command, emulator = words[0], emulators[words[1]]
    if command == "unplug":
        down_s = float(words[2])
        return lambda: _start_task(emulator.disconnect(down_s))
    if command == "corrupt":
        n = int(words[2])
        return lambda: emulator.corrupt_scans(n)
    if command == "garbage":
        n = int(words[2])
        return lambda: emulator.garbage_scans(n)
    if command == "delay":
        n, delay_s = int(words[2]), float(words[3])
        return lambda: emulator.delay_scans(n, delay_s)
    raise ValueError("unknown command (unplug, corrupt, garbage, delay)")


def _home(text: str) -> tuple[float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError("expected LAT,LON,ALT") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError("expected LAT,LON,ALT (three finite numbers)")
    return values  # type: ignore[return-value]


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m sitl.scip_bridge", description=__doc__.split("\n", 1)[0])
    p.add_argument("--vehicle", required=True,
                   help="pymavlink URL of this bridge's link to the SITL vehicle, e.g. udpin:127.0.0.1:14560 "
                        "(the vehicle then has --gcs udpout:127.0.0.1:14560)")
    p.add_argument("--world", required=True, help="world YAML the scanners see (sitl.world)")
    p.add_argument("--home", type=_home, required=True, help="the vehicle's --home LAT,LON,ALT (truth origin)")
    p.add_argument("--sensor", type=SensorSpec.parse, action="append", required=True,
                   help="NAME,MODEL,X,Y,Z,ROLL,PITCH,YAW_DEG,PORT: a scanner on that mount (body FRD, m and deg) "
                        "served on TCP 127.0.0.1:PORT (repeatable)")
    p.add_argument("--seed", type=int, default=0, help="range noise seed; sensor i uses SEED + i")
    p.add_argument("--faults-from-stdin", action="store_true",
                   help="read fault commands from stdin (unplug/corrupt/garbage/delay; see the module docstring)")
    args = p.parse_args(argv)
    ports = [s.port for s in args.sensor]
    if len(set(ports)) != len(ports):
        p.error("every --sensor needs its own PORT")
    if args.seed < 0:
        p.error("--seed must be >= 0")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        return asyncio.run(serve(args))
    except SchemaError as exc:
        print(f"sitl.scip_bridge: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a port in use, a bad URL
        print(f"sitl.scip_bridge: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
