"""Commands addressed to the companion itself: COMMAND_LONG with ``target_system`` and
``target_component`` this companion's (``vehicle.sysid``, ``vehicle.compid``), e.g. a ground
station asking for the EKF-SLAM return to base (the autopilot routes it to us).

Who is obeyed: the systems in ``mavlink.command_sysids`` (default ``[255]``, a ground station by
convention). A command from anyone else is refused (MAV_RESULT_DENIED) and counted; on an
unsigned link anyone who can send to it can claim sysid 255, so sign the link
(``mavlink.signing_key_file``) where that matters. Every command gets one COMMAND_ACK, sent back
to its sender: ACCEPTED, DENIED (why, as a STATUSTEXT), UNSUPPORTED (no handler for it here), or
FAILED (the handler raised: logged with its traceback and told as a STATUSTEXT, so the ground
station is not left retrying an unanswered command).

A handler answers ``None`` (done) or the reason it cannot (denied); it runs in the link's
receive path, so it must not block.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from companion.mavlink.link import MavlinkLink

log = logging.getLogger("companion.commands")

CommandHandler = Callable[[mavlink.MAVLink_command_long_message], str | None]


@dataclass
class InboundStats:
    accepted: int = 0
    denied: int = 0  # a handler's refusal
    unsupported: int = 0  # no handler for that command
    failed: int = 0  # the handler raised
    refused_senders: int = 0  # from a system not in mavlink.command_sysids


class InboundCommands:
    """Answers the COMMAND_LONGs addressed to this companion (see the module docstring)."""

    def __init__(self, link: MavlinkLink, allowed_sysids: tuple[int, ...],
                 announce: Callable[[str], None]) -> None:
        """``announce(text)``: tell the operator (a STATUSTEXT to the ground station) why a
        command was denied."""
        self.link = link
        self.allowed = frozenset(allowed_sysids)
        self.announce = announce
        self.stats = InboundStats()
        self._handlers: dict[int, CommandHandler] = {}
        link.on_addressed_command(self._on_command)

    def register(self, command: int, handler: CommandHandler) -> None:
        """Obey MAV_CMD ``command`` with ``handler`` (one per command)."""
        self._handlers[command] = handler

    def _on_command(self, msg: mavlink.MAVLink_command_long_message) -> None:
        sender = (msg.get_srcSystem(), msg.get_srcComponent())
        name = mavlink.enums["MAV_CMD"][msg.command].name if msg.command in mavlink.enums["MAV_CMD"] else str(msg.command)
        handler = self._handlers.get(msg.command)
        if sender[0] not in self.allowed:
            self.stats.refused_senders += 1
            log.warning("%s from system %d refused: not in mavlink.command_sysids", name, sender[0])
            result, why = mavlink.MAV_RESULT_DENIED, None
        elif handler is None:
            self.stats.unsupported += 1
            result, why = mavlink.MAV_RESULT_UNSUPPORTED, None
        else:
            try:
                why = handler(msg)
            except Exception as exc:  # a bug in a handler must still answer the sender
                log.exception("%s from system %d component %d: the handler failed", name, *sender)
                why = f"{name} failed: {type(exc).__name__}: {exc}"
                self.stats.failed += 1
                result = mavlink.MAV_RESULT_FAILED
            else:
                result = self._judged(name, sender, why)
        self.link.send(mavlink.MAVLink_command_ack_message(msg.command, result, 0, 0, *sender))
        if why is not None:
            self.announce(f"companion: {why}")

    def _judged(self, name: str, sender: tuple[int, int], why: str | None) -> int:
        """ACCEPTED if the handler answered None, else DENIED (counted and logged)."""
        if why is None:
            self.stats.accepted += 1
            log.info("%s from system %d component %d: accepted", name, *sender)
            return mavlink.MAV_RESULT_ACCEPTED
        self.stats.denied += 1
        log.warning("%s from system %d component %d denied: %s", name, *sender, why)
        return mavlink.MAV_RESULT_DENIED
