"""The flight recorder's channels served live to the Foxglove app over its WebSocket protocol
(``record.foxglove_server``; loopback by default), with the Foxglove SDK (``foxglove-sdk``).

The same topics, schemas and JSON documents as the recording (companion/recording/recorder.py), so
a layout made on a recording works live and the other way round. The server runs in the SDK's own
(Rust) threads; :meth:`FoxgloveLive.write` only hands it the bytes, from the recorder's writer
thread. A Foxglove app that connects gets what is logged from then on.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

from companion.recording import codec

log = logging.getLogger("companion.recording")


class FoxgloveLive:
    """A Foxglove WebSocket server on ``host``:``port`` (a sink of the recorder)."""

    name = "foxglove"

    def __init__(self, host: str, port: int) -> None:
        self.host = host
        self.port = port
        self.logged = 0
        self._server: Any = None
        self._context: Any = None
        self._channels: dict[str, Any] = {}

    def open(self, stats: Callable[[], dict[str, Any]]) -> None:
        """Start the server (OSError if the port is taken; ImportError without foxglove-sdk); the
        recorder's counters (``stats``) are not served."""
        import foxglove

        self._foxglove = foxglove
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name="uav-companion", host=self.host, port=self.port,
                                                 context=self._context)
        except RuntimeError as exc:  # the SDK reports a bind failure as RuntimeError
            raise OSError(f"Foxglove server on {self.host}:{self.port}: {exc}") from exc
        self.port = self._server.port
        log.info("Foxglove WebSocket server on ws://%s:%d", self.host, self.port)

    def write(self, topic: str, schema: codec.ChannelSchema, data: bytes, log_ns: int, publish_ns: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = self._foxglove.Channel(
                topic, schema=self._foxglove.Schema(name=schema.name, encoding=schema.encoding, data=schema.data),
                message_encoding=schema.message_encoding, context=self._context)
        channel.log(data, log_time=log_ns)
        self.logged += 1

    def flush(self) -> None:
        """Nothing to flush: the server sends as it goes."""

    def close(self) -> None:
        if self._server is not None:
            self._server.stop()
            self._server = None

    def abandon(self) -> None:
        self.close()

    def snapshot(self) -> dict[str, Any]:
        return {"foxglove_url": f"ws://{self.host}:{self.port}", "foxglove_logged": self.logged}
