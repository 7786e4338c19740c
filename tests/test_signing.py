"""MAVLink 2 signing end to end (companion/mavlink/signing.py), over real MAVLink on loopback:
the daemon's link with a key takes only correctly signed messages: unsigned, wrong-key, replayed
and forged-timestamp frames are dropped and counted, never as parse errors.
"""

from __future__ import annotations

import asyncio
import time

from companion.mavlink.link import MavlinkLink, mavlink
from companion.mavlink.signing import signing_timestamp
from tests.mavlink_peer import FakeAutopilot, make_link

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
ONE_HOUR_10US = 3600 * 100_000


def packer(key: bytes | None, link_id: int = 0, timestamp: int | None = None) -> mavlink.MAVLink:
    """A codec speaking as the autopilot (1, 1) that packs frames: unsigned, or signed with ``key``."""
    codec = mavlink.MAVLink(None, 1, 1)
    if key is not None:
        codec.signing.secret_key = key
        codec.signing.sign_outgoing = True
        codec.signing.link_id = link_id
        codec.signing.timestamp = signing_timestamp(time.time()) if timestamp is None else timestamp
    return codec


def attitude(boot_ms: int) -> mavlink.MAVLink_message:
    return mavlink.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


# -- the daemon's link -----------------------------------------------------------------------


def test_the_signed_link_takes_signed_messages_and_drops_and_counts_the_others() -> None:
    fake = FakeAutopilot(key=KEY)
    seen: list[int] = []

    async def main() -> MavlinkLink:
        link = make_link(fake.url, key=KEY)
        link.subscribe("ATTITUDE", lambda msg: seen.append(msg.time_boot_ms))
        task = asyncio.ensure_future(link.run())
        try:
            await fake.connect(link)  # signed both ways
            fake.attitude(1000)
            fake.write(attitude(1010).pack(packer(None)))  # unsigned
            fake.write(attitude(1020).pack(packer(OTHER_KEY)))  # another key
            genuine = attitude(1030).pack(fake.conn.mav)
            fake.write(genuine)
            fake.write(genuine)  # replayed: its timestamp is not newer
            stream = fake.conn.mav.signing.link_id  # a forged frame on the fake's own stream, an hour ahead
            fake.write(attitude(1040).pack(packer(OTHER_KEY, stream, signing_timestamp(time.time()) + ONE_HOUR_10US)))
            fake.attitude(1050)  # the genuine stream is not locked out by the forged timestamp
            await fake.until(lambda: 1050 in seen, "the last genuine ATTITUDE")
            return link
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    try:
        link = asyncio.run(main())
    finally:
        fake.close()
    assert seen == [1000, 1030, 1050]
    assert link.stats.unsigned_rejected == 1
    assert link.stats.bad_signatures == 3  # the other key, the replay, the forged timestamp
    assert link.stats.parse_errors == 0
    assert not [m for m in fake.received if m.get_type() == "BAD_DATA"]  # everything the link sent was signed
    assert all(m.get_signed() for m in fake.received)
