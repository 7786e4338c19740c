"""Opening the zenoh session that carries telemetry.

The daemon runs a zenoh *peer* with explicit endpoints: zenoh's defaults (listen on every
interface on a random port, multicast scouting) are wrong for a vehicle, so every value is set
here. A peer session opens even when none of its ``connect`` endpoints is reachable and keeps
retrying in the background; a *client* session fails at once without a reachable router.
"""

from __future__ import annotations

import json
import logging

import zenoh

logger = logging.getLogger("companion.telemetry")


def zenoh_config(
    mode: str,
    listen: list[str],
    connect: list[str],
    multicast_scouting: bool,
    gossip_scouting: bool,
    reconnect_period_s: float | None = None,
) -> zenoh.Config:
    """Build a zenoh configuration with every networking choice explicit.

    Args:
        mode: zenoh mode, ``"peer"`` (the daemon's normal mode) or ``"client"``.
        listen: endpoints to listen on, e.g. ``["tcp/127.0.0.1:7447"]``; an empty list
            listens nowhere (zenoh's peer default of ``tcp/[::]:0`` is replaced, not kept).
        connect: endpoints of peers or routers to connect to, e.g. ``["tcp/192.168.1.10:7447"]``.
        multicast_scouting: discover peers by UDP multicast (224.0.0.224:7446).
        gossip_scouting: learn further peers from the peers already connected.
        reconnect_period_s: retry an unreachable or lost ``connect`` endpoint every this many
            seconds; None keeps zenoh's default (1 s, doubling up to 4 s).

    Raises:
        zenoh.ZError: an unknown mode or a malformed endpoint (zenoh validates both).
    """
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(mode))
    config.insert_json5("listen/endpoints", json.dumps(list(listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(connect)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    config.insert_json5("scouting/gossip/enabled", json.dumps(gossip_scouting))
    if reconnect_period_s is not None:
        period_ms = max(1, round(reconnect_period_s * 1e3))
        config.insert_json5("connect/retry", json.dumps(
            {"period_init_ms": period_ms, "period_max_ms": period_ms, "period_increase_factor": 1.0}))
    return config


def open_session(
    mode: str,
    listen: list[str],
    connect: list[str],
    multicast_scouting: bool,
    gossip_scouting: bool,
    reconnect_period_s: float | None = None,
) -> zenoh.Session:
    """Open a zenoh session configured by :func:`zenoh_config` (same arguments).

    Blocks for at most about half a second in peer mode while zenoh makes a first attempt on
    the ``connect`` endpoints; call it before the asyncio loop starts, or in an executor.
    The caller owns the session and closes it with ``session.close()``.

    Raises:
        zenoh.ZError: invalid configuration, a listen endpoint that cannot be bound, or
            (client mode) no reachable router.
    """
    config = zenoh_config(mode, listen, connect, multicast_scouting, gossip_scouting, reconnect_period_s)
    session = zenoh.open(config)
    logger.info(
        "zenoh %s session open: listen=%s connect=%s multicast_scouting=%s gossip_scouting=%s",
        mode,
        listen,
        connect,
        multicast_scouting,
        gossip_scouting,
    )
    return session
