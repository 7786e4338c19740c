"""MAVLink 2 signing on one pymavlink codec: sign everything sent, take only what is signed.

Shared by the daemon's link (companion/mavlink/link.py) and the built-in vehicle's companion link
(sitl/vehicle.py), so both ends apply the same rules. :func:`require_signatures` sets a codec up so that:

- every message it sends is signed with the key, with the codec's ``link_id``, and with a
  timestamp (10 us units since 2015-01-01) that never falls behind the wall clock: pymavlink only
  adds one per message sent, so a long-running sender would otherwise lag, and a receiver that
  starts later refuses a new stream more than a minute behind its own clock;
- a message it receives is taken only if it is signed with the key and its timestamp is newer than
  the last one taken from the same stream (link id, sysid, compid), as the MAVLink 2 signing
  specification asks (pymavlink's check); a new stream may start at most one minute behind the
  receiver's clock. The signature is checked before the stream's timestamp is recorded, as the
  MAVLink C library does: pymavlink records it first, so one forged frame with a far-future
  timestamp would make every genuine frame of that stream look replayed;
- anything else (unsigned, a wrong key, a replayed or old timestamp) is refused: pymavlink turns
  it into a BAD_DATA message whose reason is :data:`REFUSED` (see :func:`is_refused`), and
  ``on_refused(signed)`` is called for it, ``signed`` False for an unsigned message and True for a
  bad signature or timestamp. No message type is let through unsigned.
"""

from __future__ import annotations

import hashlib
import time
import types
from collections.abc import Callable

from pymavlink.dialects.v20 import ardupilotmega as mavlink

SIGNING_EPOCH = 1420070400  # 2015-01-01T00:00Z: signing timestamps count 10 us units from there
REFUSED = "Invalid signature"  # pymavlink's BAD_DATA reason for a message the signing check refused
SIGNATURE_LEN = 6


def signing_timestamp(unix_s: float) -> int:
    """The MAVLink 2 signing timestamp (10 us units since 2015-01-01) of Unix time ``unix_s``."""
    return int(max(unix_s - SIGNING_EPOCH, 0.0) * 100_000)


class WallClockSigning(mavlink.MAVLinkSigning):
    """pymavlink's signing state whose ``timestamp`` is never behind the wall clock."""

    def __init__(self) -> None:
        self._timestamp = 0
        super().__init__()

    @property  # type: ignore[override]
    def timestamp(self) -> int:
        return max(self._timestamp, signing_timestamp(time.time()))

    @timestamp.setter
    def timestamp(self, value: int) -> None:
        self._timestamp = value


def is_refused(msg: mavlink.MAVLink_message) -> bool:
    """Whether ``msg`` is the BAD_DATA pymavlink makes of a message the signing check refused."""
    return msg.get_type() == "BAD_DATA" and getattr(msg, "reason", None) == REFUSED


def require_signatures(codec: mavlink.MAVLink, key: bytes, link_id: int, on_refused: Callable[[bool], None],
                       streams: dict[tuple[int, int, int], int] | None = None) -> None:
    """Set ``codec`` up to sign with ``key`` and take signed messages only (see the module docstring).

    ``streams`` (link id, sysid, compid) -> newest timestamp taken: pass the same dict to every
    codec of one link, so that a reopened port still refuses what the previous one took."""
    signing = WallClockSigning()
    if streams is not None:
        signing.stream_timestamps = streams
    signing.secret_key = key
    signing.sign_outgoing = True
    signing.link_id = link_id
    signing.allow_unsigned_callback = _Refuser(on_refused)
    codec.signing = signing
    checked_in_pymavlink_order = codec.check_signature

    def check_signature(self: mavlink.MAVLink, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        digest = hashlib.sha256(key + bytes(msgbuf[:-SIGNATURE_LEN])).digest()[:SIGNATURE_LEN]
        return digest == bytes(msgbuf[-SIGNATURE_LEN:]) and checked_in_pymavlink_order(
            msgbuf, src_system, src_component)

    codec.check_signature = types.MethodType(check_signature, codec)


class _Refuser:
    """pymavlink's ``allow_unsigned_callback``: refuses every message it is asked about, telling
    ``on_refused`` whether it was signed. pymavlink asks about unsigned messages and, right after
    counting it in ``badsig_count``, about badly signed ones."""

    def __init__(self, on_refused: Callable[[bool], None]) -> None:
        self._on_refused = on_refused
        self._bad_seen = 0

    def __call__(self, codec: mavlink.MAVLink, msg_id: int) -> bool:
        signed = codec.signing.badsig_count != self._bad_seen
        self._bad_seen = codec.signing.badsig_count
        self._on_refused(signed)
        return False
