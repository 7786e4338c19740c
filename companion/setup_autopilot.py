"""`companion setup-autopilot`: check, and with ``--apply`` write, the autopilot parameters the
configured pipelines need (``companion.mavlink.requirements``).

It connects like the daemon (``mavlink.url`` or ``--mavlink``), identifies the firmware
(HEARTBEAT, AUTOPILOT_VERSION), reads every parameter and prints the ones that differ from what
the companion needs, with the reason and whether the autopilot reads it at boot only. A dry run
writes nothing. ``--apply`` writes each with PARAM_SET and checks the value read back;
``--param NAME=VALUE`` adds parameters of your own (``companion sitl --ardupilot`` adds the SITL's
error sources this way). ``--reboot`` then reboots the autopilot if a written parameter needs it
and it is disarmed, and keeps the link open until the autopilot drops it (ArduPilot 4.0 SITL
halts with "Short write on UART" when a client hangs up during its reboot).

Exit status: 0 nothing differs (or everything was written and read back), 3 differences remain
(dry run), 1 no autopilot or a write failed, 2 bad configuration.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field

from companion import clock
from companion.config import Config
from companion.health import Health
from companion.mavlink.autopilot import AutopilotState
from companion.mavlink.commands import CommandFailed, Commander
from companion.mavlink.link import MavlinkLink, load_signing_key, mavlink
from companion.mavlink.params import ParamError, ParameterClient
from companion.mavlink.requirements import Difference, Requirement, differences, requirements

EXIT_OK, EXIT_FAILED, EXIT_DIFFERENCES = 0, 1, 3
REBOOT_DROP_S = 10.0  # after the reboot command, wait this long at most for the autopilot to drop the link


@dataclass
class SetupOutcome:
    """What one run found and did (also what the harness and tests read)."""

    firmware: str = ""
    parameter_count: int = 0
    differences: list[Difference] = field(default_factory=list)
    written: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    rebooted: bool = False

    @property
    def reboot_needed(self) -> list[str]:
        return [d.name for d in self.differences if d.reboot and d.name in self.written]


def parse_param_assignments(items: list[str]) -> list[Requirement]:
    """``NAME=VALUE`` strings as requirements (ValueError on a malformed one)."""
    extra = []
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name or not name.replace("_", "").isalnum():
            raise ValueError(f"--param {item!r}: expected NAME=VALUE")
        extra.append(Requirement(name.upper(), float(value), "asked for with --param"))
    return extra


def format_table(diffs: list[Difference]) -> list[str]:
    rows = [("parameter", "now", "wanted", "reboot", "why")]
    rows += [(d.name, f"{d.current:g}", f"{d.wanted:g}", "yes" if d.reboot else "", d.why) for d in diffs]
    widths = [max(len(r[i]) for r in rows) for i in range(4)]
    return ["  ".join(cell.ljust(w) for cell, w in zip(r[:4], widths)) + "  " + r[4] for r in rows]


async def setup_autopilot(cfg: Config, url: str, *, apply: bool, reboot: bool, extra: list[Requirement],
                          timeout_s: float, out: Callable[[str], None]) -> tuple[int, SetupOutcome]:
    """Run the check (and the writes); (exit status, outcome)."""
    outcome = SetupOutcome()
    health = Health(clock.now)
    key = cfg.load_referenced("mavlink.signing_key_file", cfg.mavlink.signing_key_file, load_signing_key) if cfg.mavlink.signing_key_file else None
    link = MavlinkLink(cfg.mavlink, cfg.vehicle, url, health, key)
    state = AutopilotState(link)
    commander = Commander(link, state, cfg.mavlink)
    params = ParameterClient(link, lambda: state.firmware)
    task = asyncio.get_running_loop().create_task(link.run(), name="link")
    try:
        if not await _until(lambda: link.connected and state.firmware is not None, timeout_s):
            out(f"no autopilot HEARTBEAT on {url} within {timeout_s:g} s")
            return EXIT_FAILED, outcome
        await commander.request_autopilot_version()  # waits for it; without it the parameters still decide
        assert state.firmware is not None
        outcome.firmware = state.firmware.label
        values = await params.fetch_all(timeout_s)
        outcome.parameter_count = len(values)
        needed = requirements(state.firmware, cfg, values)
        unknown = [r.name for r in extra if r.name not in values]
        outcome.differences = differences(needed + [r for r in extra if r.name in values], values)
        out(f"autopilot: {outcome.firmware} (sysid {link.ids.autopilot_sysid}) on {url}; {len(values)} parameters read")
        out(f"needed by this config: {', '.join(r.name for r in needed) or 'nothing (no pipeline gives the position)'}")
        for name in unknown:
            out(f"{name}: no such parameter on this autopilot (ignored)")
        if not outcome.differences:
            out("every parameter is as the companion needs it: nothing to change")
            return (EXIT_FAILED if unknown else EXIT_OK), outcome
        for line in format_table(outcome.differences):
            out(line)
        if not apply:
            out(f"{len(outcome.differences)} differ. Dry run: nothing written; --apply writes them.")
            return EXIT_DIFFERENCES, outcome
        await _write_all(params, outcome, out)
        if outcome.failed:
            return EXIT_FAILED, outcome
        if outcome.reboot_needed:
            if reboot:
                await _reboot(link, state, commander, outcome, out)
            else:
                out(f"reboot the autopilot for {', '.join(outcome.reboot_needed)} to take effect "
                    "(--reboot does it when disarmed)")
        return (EXIT_FAILED if unknown else EXIT_OK), outcome
    except ParamError as exc:
        out(f"parameters: {exc}")
        return EXIT_FAILED, outcome
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


async def _write_all(params: ParameterClient, outcome: SetupOutcome, out: Callable[[str], None]) -> None:
    for d in outcome.differences:
        try:
            got = await params.write(d.name, d.wanted)
        except ParamError as exc:
            outcome.failed.append(d.name)
            out(f"{d.name}: FAILED: {exc}")
            continue
        outcome.written.append(d.name)
        out(f"{d.name}: {d.current:g} -> {got:g} (read back)")


async def _reboot(link: MavlinkLink, state: AutopilotState, commander: Commander, outcome: SetupOutcome,
                  out: Callable[[str], None]) -> None:
    if state.armed:
        out(f"armed: not rebooting; reboot for {', '.join(outcome.reboot_needed)} once landed and disarmed")
        return
    try:
        await commander.command(mavlink.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1)
    except CommandFailed as exc:
        out(f"reboot: {exc}")
        return
    dropped = await _until(lambda: not link.connected, REBOOT_DROP_S)
    outcome.rebooted = True
    out(f"rebooting the autopilot for {', '.join(outcome.reboot_needed)}"
        + ("" if dropped else " (the link did not drop: check that it restarted)"))


async def _until(condition: Callable[[], bool], timeout_s: float) -> bool:
    deadline = clock.now() + timeout_s
    while not condition():
        if clock.now() > deadline:
            return False
        await asyncio.sleep(0.05)
    return True
