"""The built-in simulated vehicle process: an ArduPilot-Copter-4.x-like autopilot on MAVLink 2.

``python -m sitl.vehicle --companion udpin:127.0.0.1:14555 [--gcs udpout:127.0.0.1:14550] ...``

It wraps :class:`sitl.copter.SimulatedCopter` (physics, flight controller, estimator), or with
``--vehicle plane`` :class:`sitl.plane.SimulatedPlane` (an ArduPlane-like fixed wing: HEARTBEAT
type MAV_TYPE_FIXED_WING, ArduPlane custom modes), and speaks
MAVLink 2 as system ``--sysid``, component 1 (MAV_COMP_ID_AUTOPILOT1) on one pymavlink connection
per link: the companion link and any number of ground-station links. Like ArduPilot, each link
has its own stream intervals (SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM), commands are ACKed on
the link they came in on, STATUSTEXT goes to every link, and messages not addressed to this
vehicle are forwarded to the other links (TIMESYNC excepted: it is answered, never forwarded).

Frames (companion/frames.py): world = MAVLink LOCAL_NED at the EKF origin, body FRD, quaternions
[w, x, y, z]. Ground truth (SIM_STATE, flight log) is relative to the ``--home`` anchor, which is
the same frame once the companion sets the EKF origin there.

Time: simulation time t (s) advances in ticks of ``--tick``. In real time (default)
t = time.monotonic() - t0, paced by the wall clock. With ``--lockstep`` the companion's clock is
driven by the vehicle, which makes runs deterministic for a seed:

1. until a HEARTBEAT from a component other than 1 arrives on the companion link, send our
   HEARTBEAT on every link once a wall-clock second; then t = 0;
2. send TIMESYNC(tc1=0, ts1=round(t*1e9)) on the companion link and handle incoming messages
   (all links, arrival order) until the reply, a TIMESYNC with tc1 != 0 and that ts1, arrives
   on the companion link; what the companion sent after its reply is handled at the next tick;
3. send everything due at t, step the copter one tick, t += tick, and go to 2 (until
   ``--seconds``). A reply missing for 15 s is reported on stderr, for 60 s it ends the run.

At exit (``--seconds`` reached, SIGTERM or SIGINT) the flight log (sitl/flight_log.py) is written
to ``--log`` and the process exits 0; a lockstep reply missing for 60 s exits 3.

Signing: with ``--signing-key FILE`` (the daemon's ``mavlink.signing_key_file``) the companion
link signs everything it sends and takes only messages signed with that key, with timestamps
that only go forward (companion/mavlink/signing.py, the daemon's rules); the others are dropped and
counted in the flight log's ``signing`` (``unsigned_rejected``, ``bad_signatures``), and the first
is reported on stderr. An unsigned companion can then neither command the vehicle nor, in
lockstep, start it. Ground-station links stay unsigned; what they send for the companion is
forwarded as it came, as a router does.

The process is split along its parts, which :class:`Vehicle` (core.py) puts together:

- link.py: one MAVLink channel (connection, stream schedule, clock mapping);
- run_loop.py: simulation time, the real-time and lockstep loops, stopping;
- receiving.py: routing incoming messages and handling those that are not commands;
- commands.py: COMMAND_LONG / COMMAND_INT and their ACKs;
- state.py: what the vehicle announces and logs when its state changes;
- messages.py: the outgoing messages (streams and answers to requests);
- cli.py: the command line (:func:`parse_args`, :func:`main`; ``__main__.py`` runs it).
"""

import os

os.environ.setdefault("MAVLINK20", "1")  # before pymavlink picks its wire protocol (every part imports it)

from sitl.vehicle.cli import main, parse_args  # noqa: E402
from sitl.vehicle.core import Vehicle, VehicleConfig  # noqa: E402
from sitl.vehicle.link import Link  # noqa: E402

__all__ = ["Link", "Vehicle", "VehicleConfig", "main", "parse_args"]
