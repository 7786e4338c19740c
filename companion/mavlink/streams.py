"""The streams the companion needs from the autopilot, negotiated with what its firmware offers.

Each *need* (attitude, IMU, the autopilot's position, ..., simulator truth) lists options in
order of preference; an option is the message, or the messages together, that satisfy it:

- IMU: HIGHRES_IMU; else SCALED_IMU, RAW_IMU (ArduPilot only: its RAW_IMU carries scaled mG and
  mrad/s, PX4's raw sensor counts), SCALED_IMU2 (ArduPilot 4.0 streams no HIGHRES_IMU);
- barometer (off unless asked): SCALED_PRESSURE, for the scaled IMU messages that carry no
  pressure altitude (companion/mavlink/autopilot.py attaches it to their samples);
- simulator truth: SIM_STATE; else SIMSTATE with SCALED_PRESSURE (ArduPilot SITL before SIM_STATE:
  SIMSTATE has no altitude, the SITL barometer gives it, see ``sitl.truth``).

Every (re)connection, after the autopilot's first HEARTBEAT: ask for the first option of every
need with SET_MESSAGE_INTERVAL. A refusal (MAV_RESULT_FAILED / DENIED) moves that need to its next
option, and so does no COMMAND_ACK at all. An option accepted for a need that has alternatives
must then deliver within :data:`VERIFY_S` (else the next one is tried: some firmware accepts an
interval for a message it never sends). An ArduPilot that does not know SET_MESSAGE_INTERVAL
(MAV_RESULT_UNSUPPORTED) gets its legacy REQUEST_DATA_STREAM groups instead, at the highest rate
any need of the group asks for (PX4 has no such groups: there it is a refusal). The outcome is reported as the ``streams`` health component
and on telemetry (``chosen``).

Then the streams a live autopilot always sends (:data:`ALWAYS_SENT`: attitude and IMU; the
position, for one, stops while the EKF has none) are watched: one whose last message is older
than the autopilot's last HEARTBEAT by more than :func:`stall_after_s` (five periods, at least
:data:`MIN_STALL_S`, on two checks in a row; a hung autopilot sends no HEARTBEAT either, and is
not asked) is asked for again as it was chosen, and if that is refused or it still does not come,
the whole negotiation starts again (at most every :data:`REASK_EVERY_S`). That is how an autopilot that
rebooted faster than the link timeout is found: it comes back streaming nothing until asked, so
without this no boot time would ever show the reboot.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass

from companion import clock
from companion.config import StreamRatesConfig
from companion.health import Health, State
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import Commander
from companion.mavlink.link import MavlinkLink, mavlink, run_per_connection

log = logging.getLogger("companion.streams")

VERIFY_S = 2.0  # an accepted option of a need with alternatives must deliver within this
MIN_STALL_S = 0.5  # a chosen stream silent this long (and five of its periods) has stopped
REASK_EVERY_S = 5.0  # a stopped stream is asked for again at most this often
WATCH_PERIOD_S = 0.25
ALWAYS_SENT = ("attitude", "imu")  # needs whose messages a live autopilot streams in any state
ACCEPTED, REFUSED, UNSUPPORTED = "accepted", "refused", "unsupported"

# ArduPilot's REQUEST_DATA_STREAM groups (ArduCopter/GCS_Mavlink.cpp, STREAM_*_msgs; SITL builds
# that have SIM_STATE stream it in EXTRA1 beside SIMSTATE).
LEGACY_GROUPS: dict[str, int] = {
    **dict.fromkeys(("RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "SCALED_PRESSURE"), mavlink.MAV_DATA_STREAM_RAW_SENSORS),
    **dict.fromkeys(("GPS_RAW_INT", "GPS2_RAW", "SYS_STATUS"), mavlink.MAV_DATA_STREAM_EXTENDED_STATUS),
    **dict.fromkeys(("LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"), mavlink.MAV_DATA_STREAM_POSITION),
    **dict.fromkeys(("ATTITUDE", "SIMSTATE", "SIM_STATE"), mavlink.MAV_DATA_STREAM_EXTRA1),
    **dict.fromkeys(("EKF_STATUS_REPORT", "SYSTEM_TIME"), mavlink.MAV_DATA_STREAM_EXTRA3),
}


@dataclass(frozen=True)
class StreamNeed:
    """A need, its rate (Hz) and its options (each: the message names that together satisfy it)."""

    name: str
    rate_hz: float
    options: tuple[tuple[str, ...], ...]


def stream_needs(rates: StreamRatesConfig, autopilot: str | None) -> list[StreamNeed]:
    """The needs of this config for this autopilot flavour (0 Hz needs left out)."""
    px4 = autopilot == "PX4"
    imu = (("HIGHRES_IMU",), ("SCALED_IMU",)) if px4 else (
        ("HIGHRES_IMU",), ("SCALED_IMU",), ("RAW_IMU",), ("SCALED_IMU2",))
    needs = [
        StreamNeed("attitude", rates.attitude, (("ATTITUDE",),)),
        StreamNeed("imu", rates.imu, imu),
        StreamNeed("local_position", rates.local_position, (("LOCAL_POSITION_NED",),)),
        StreamNeed("gps_raw", rates.gps_raw, (("GPS_RAW_INT",),)),
        StreamNeed("gps2_raw", rates.gps2_raw, (("GPS2_RAW",),)),
        StreamNeed("home_position", rates.home_position, (("HOME_POSITION",),)),
        StreamNeed("pressure", rates.pressure, (("SCALED_PRESSURE",),)),
        StreamNeed("estimator_status", rates.estimator_status,
                   (("ESTIMATOR_STATUS",),) if px4 else (("EKF_STATUS_REPORT",),)),
        StreamNeed("sim_state", rates.sim_state, (("SIM_STATE",), ("SIMSTATE", "SCALED_PRESSURE"))),
    ]
    return [need for need in needs if need.rate_hz > 0]


def _raise_if_cancelling() -> None:
    """Python 3.11's asyncio.wait_for can swallow a cancellation that meets a result (an ACK arriving
    as the connection is replaced): a loop that never ends must still stop once cancelled."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


def stall_after_s(rate_hz: float) -> float:
    """How long a stream at ``rate_hz`` may be silent before it counts as stopped (s)."""
    return max(MIN_STALL_S, 5.0 / rate_hz)


def message_id(name: str) -> int:
    return getattr(mavlink, f"MAVLINK_MSG_ID_{name}")


class StreamNegotiator:
    """Supervised task body: negotiates the streams again after every (re)connection."""

    def __init__(self, link: MavlinkLink, state: AutopilotState, commander: Commander, rates: StreamRatesConfig,
                 health: Health) -> None:
        self.link = link
        self.state = state
        self.commander = commander
        self.rates = rates
        self.health = health
        self.chosen: dict[str, str | None] = {}  # need -> "MSG[+MSG] @ Hz via interval|legacy", None: unmet
        self.negotiations = 0  # completed negotiations and successful re-asks
        self._last_seen: dict[str, float] = {}
        self._watched: dict[str, tuple[float, float]] = {}  # chosen message -> (rate Hz, stall time s)
        self._legacy_groups: dict[int, float] = {}  # REQUEST_DATA_STREAM group -> rate Hz, when used
        self._restart = asyncio.Event()
        link.on_connect(self._restart.set)
        for name in {m for need in stream_needs(rates, None) + stream_needs(rates, "PX4")
                     for option in need.options for m in option}:
            link.subscribe(name, self._seen)
        health.report("streams", State.LOST, "not requested yet")

    def _seen(self, msg: mavlink.MAVLink_message) -> None:
        self._last_seen[msg.get_type()] = clock.now()

    def _delivering(self, option: tuple[str, ...], since: float) -> bool:
        return all(self._last_seen.get(name, -1.0) >= since for name in option)

    async def run(self) -> None:
        await run_per_connection(self._restart, self._negotiate_and_watch)

    async def _negotiate_and_watch(self) -> None:
        """Negotiate, then ask again whenever a chosen stream stops (see the module docstring)."""
        await self.negotiate()
        while True:
            _raise_if_cancelling()
            stalled = await self._until_stalled()
            asked_at = clock.now()
            if not await self._ask_again(stalled, asked_at):
                await self.negotiate()
            await clock.sleep_until(asked_at + REASK_EVERY_S)

    async def _until_stalled(self) -> list[str]:
        """The watched messages once they have stopped on two checks in a row (see the module docstring)."""
        previous: list[str] = []
        while True:
            _raise_if_cancelling()
            await asyncio.sleep(WATCH_PERIOD_S)
            heard = self.link.last_heartbeat
            stalled = [] if heard is None else sorted(
                name for name, (_, after) in self._watched.items()
                if heard - self._last_seen.get(name, -float("inf")) > after)
            if stalled and stalled == previous:
                log.warning("streams stopped while the autopilot still sends HEARTBEATs (%s): asking again",
                            ", ".join(stalled))
                self.health.report("streams", State.DEGRADED, f"stopped: {', '.join(stalled)}; asking again")
                return stalled
            previous = stalled

    async def _ask_again(self, names: list[str], asked_at: float) -> bool:
        """Ask for the stopped messages again as they were chosen; whether they deliver again."""
        if self._legacy_groups:
            self._send_legacy_groups()
        else:
            results = [await self._set_interval(name, self._watched[name][0]) for name in names]
            if any(result != ACCEPTED for result in results):
                return False
        await self._until_delivering([tuple(names)], asked_at)
        if not self._delivering(tuple(names), asked_at):
            return False
        self._finish()
        return True

    async def negotiate(self) -> None:
        """Ask for every need; see the module docstring for the order of things."""
        needs = stream_needs(self.rates, self.link.autopilot)
        self._watched, self._legacy_groups = {}, {}  # (chosen keeps the last outcome of each need until this one replaces it)
        pending = {need.name: list(need.options) for need in needs}
        by_name = {need.name: need for need in needs}
        while pending:
            asked_at = clock.now()
            to_verify: dict[str, tuple[str, ...]] = {}
            for name in list(pending):
                need = by_name[name]
                outcome = await self._try_next_option(need, pending[name])
                if outcome == UNSUPPORTED:
                    await self._legacy(needs)
                    return self._finish()
                if outcome is None:  # no option left
                    self.chosen[name] = None
                    del pending[name]
                elif len(need.options) > 1:
                    to_verify[name] = outcome
                else:
                    self._choose(need, outcome, f"{'+'.join(outcome)} @ {need.rate_hz:g} Hz")
                    del pending[name]
            if not to_verify:
                break
            await self._until_delivering(list(to_verify.values()), asked_at)
            for name, option in to_verify.items():
                if self._delivering(option, asked_at):
                    self._choose(by_name[name], option, f"{'+'.join(option)} @ {by_name[name].rate_hz:g} Hz")
                    del pending[name]
                else:
                    log.warning("stream %s: %s accepted but not delivered within %g s; trying the next option",
                                name, "+".join(option), VERIFY_S)
                    await self._stop(option)
        self._finish()

    async def _try_next_option(self, need: StreamNeed, options: list[tuple[str, ...]]) -> tuple[str, ...] | str | None:
        """Request the next option of ``need`` that the autopilot accepts: that option, UNSUPPORTED
        (SET_MESSAGE_INTERVAL itself is unknown to this ArduPilot), or None (no option left)."""
        while options:
            option = options.pop(0)
            results = [await self._set_interval(name, need.rate_hz) for name in option]
            if UNSUPPORTED in results:
                return UNSUPPORTED
            if all(r == ACCEPTED for r in results):
                return option
            log.info("stream %s: %s refused; trying the next option", need.name, "+".join(option))
            await self._stop(tuple(n for n, r in zip(option, results) if r == ACCEPTED))
        return None

    async def _set_interval(self, name: str, rate_hz: float) -> str:
        result = await self.commander.command_result(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id(name),
                                                     1e6 / rate_hz)
        if result == mavlink.MAV_RESULT_UNSUPPORTED and self.link.autopilot != "PX4":
            return UNSUPPORTED
        return ACCEPTED if result == mavlink.MAV_RESULT_ACCEPTED else REFUSED

    async def _stop(self, option: tuple[str, ...]) -> None:
        for name in option:
            await self.commander.command_result(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, message_id(name), -1)

    async def _legacy(self, needs: list[StreamNeed]) -> None:
        """REQUEST_DATA_STREAM for the groups holding each need's first option that has one."""
        log.warning("the autopilot does not take SET_MESSAGE_INTERVAL: requesting legacy stream groups")
        group_rates: dict[int, float] = {}
        for need in needs:
            option = next((o for o in need.options if all(m in LEGACY_GROUPS for m in o)), None)
            if option is None:
                self.chosen[need.name] = None
                continue
            for name in option:
                group = LEGACY_GROUPS[name]
                group_rates[group] = max(group_rates.get(group, 0.0), need.rate_hz)
            self._choose(need, option, f"{'+'.join(option)} via REQUEST_DATA_STREAM")
        self._legacy_groups = group_rates
        self._send_legacy_groups()

    def _send_legacy_groups(self) -> None:
        target = self.link.target()
        for group, rate in sorted(self._legacy_groups.items()):
            self.link.send(mavlink.MAVLink_request_data_stream_message(*target, group, max(1, round(rate)), 1))

    async def _until_delivering(self, options: list[tuple[str, ...]], since: float) -> None:
        """Until every option delivers (since daemon time ``since``), or VERIFY_S has passed."""
        deadline = clock.now() + VERIFY_S
        while clock.now() < deadline and not all(self._delivering(o, since) for o in options):
            await asyncio.sleep(WATCH_PERIOD_S)

    def _choose(self, need: StreamNeed, option: tuple[str, ...], how: str) -> None:
        """``option`` serves ``need`` (``how``, for telemetry); its messages are watched from now on
        if the need is one of :data:`ALWAYS_SENT`."""
        self.chosen[need.name] = how
        if need.name == "imu":
            self.state.imu_source = option[0]
        for name in option if need.name in ALWAYS_SENT else ():
            self._watched[name] = (need.rate_hz, stall_after_s(need.rate_hz))
            self._last_seen[name] = max(self._last_seen.get(name, -float("inf")), clock.now())  # grace: from now

    def _finish(self) -> None:
        self.negotiations += 1
        unmet = sorted(name for name, how in self.chosen.items() if how is None)
        summary = "; ".join(f"{name}: {how}" for name, how in self.chosen.items() if how is not None)
        log.info("streams: %s%s", summary, f"; unavailable: {', '.join(unmet)}" if unmet else "")
        if unmet:
            self.health.report("streams", State.DEGRADED, f"unavailable: {', '.join(unmet)}")
        else:
            self.health.report("streams", State.OK, summary)
