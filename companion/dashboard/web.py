"""The dashboard's web server: the page, its assets and the event stream, nothing else.

Plain asyncio HTTP/1.1, one request per connection: ``GET /`` (the page), ``GET /static/NAME``
(its scripts, style sheet and icon; the icon also as ``/favicon.ico``, where browsers look
for it without a link) and ``GET /events`` (server-sent events: every hub event as one
``data:`` line, ``retry: 1000`` so the browser reconnects within a second). The dashboard is
read-only and so is the server: another method is 405, another path 404. Playing a recording
(``--play``), it also takes ``POST /playback`` (a JSON request to the player: play, pause, seek,
speed; the answer is the player's state), only with ``Content-Type: application/json`` and no
foreign ``Origin``, so that another site's page cannot drive it. Bound to loopback
(the default) it answers only requests whose Host header names loopback, so that a web page
elsewhere cannot read the telemetry through DNS rebinding. The assets are package data (no
CDN: the field laptop may be offline) and a Content-Security-Policy keeps the page to them.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
from collections.abc import Callable
from importlib import resources
from typing import Any

from companion.dashboard.hub import TelemetryHub

log = logging.getLogger("companion.dashboard")

REQUEST_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 1.0  # open connections get this long to end when the server stops
MAX_REQUEST_HEAD = 16 * 1024  # bytes of request line + headers
CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                 ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml"}
SECURITY_HEADERS = (
    "Content-Security-Policy: default-src 'self'; img-src 'self' data:; base-uri 'none'; form-action 'none'; "
    "frame-ancestors 'none'\r\n"
    "X-Content-Type-Options: nosniff\r\n"
    "Referrer-Policy: no-referrer\r\n"
)
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "[::1]")
MAX_CONTROL_BODY = 1024  # bytes of a POST /playback request
Control = Callable[[dict[str, Any]], dict[str, Any]]  # a request -> the state after it; ValueError: refused


def load_assets() -> dict[str, tuple[bytes, str]]:
    """{URL path: (body, content type)} of the page and every file in ``static/``."""
    assets: dict[str, tuple[bytes, str]] = {}
    for item in (resources.files(__package__) / "static").iterdir():
        suffix = "." + item.name.rsplit(".", 1)[-1]
        if item.is_file() and suffix in CONTENT_TYPES:
            assets[f"/static/{item.name}"] = (item.read_bytes(), CONTENT_TYPES[suffix])
    assets["/"] = assets["/static/index.html"]
    assets["/favicon.ico"] = assets["/static/favicon.svg"]
    return assets


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a bind address or name) is loopback only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def host_name(host_header: str) -> str:
    """The name in a Host header without the port: ``[::1]:8080`` -> ``[::1]``."""
    if host_header.startswith("["):
        return host_header[:host_header.find("]") + 1]
    return host_header.rsplit(":", 1)[0]


class DashboardServer:
    """Serves one hub's page and events on ``host``:``port`` (0 = any free port); with
    ``control`` (a playback), also ``POST /playback``."""

    def __init__(self, hub: TelemetryHub, host: str, port: int, control: Control | None = None) -> None:
        self.hub = hub
        self.control = control
        self.host = host
        self.port = port
        self.assets = load_assets()
        self._check_host = is_loopback(host)
        self._server: asyncio.Server | None = None
        self._handlers: dict[asyncio.Task, asyncio.StreamWriter] = {}
        self._closing = False

    async def start(self) -> int:
        """Listen; returns the bound port."""
        self._server = await asyncio.start_server(self._handle, self.host, self.port, limit=MAX_REQUEST_HEAD)
        self.port = self._server.sockets[0].getsockname()[1]
        return self.port

    async def stop(self) -> None:
        """Stop listening and end every open connection (event streams included)."""
        self._closing = True
        if self._server is not None:
            self._server.close()
        for writer in self._handlers.values():
            writer.close()  # a handler reading a request sees the end of the stream
        for browser in self.hub.browsers:
            browser.wake.set()  # an event stream sees _closing
        if self._handlers:
            await asyncio.wait(list(self._handlers), timeout=STOP_TIMEOUT_S)

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers[task] = writer
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), REQUEST_TIMEOUT_S)
            await self._answer(head.decode("latin-1"), reader, writer)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError, ConnectionError):
            pass  # a client that went away or sent garbage: nothing to answer
        finally:
            del self._handlers[task]
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()

    async def _answer(self, head: str, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        request_line, *header_lines = head.split("\r\n")
        parts = request_line.split(" ")
        if len(parts) != 3:
            return await _respond(writer, "400 Bad Request", b"bad request\n")
        method, target, _ = parts
        headers = {name.strip().lower(): value.strip()
                   for name, sep, value in (line.partition(":") for line in header_lines) if sep}
        if self._check_host and host_name(headers.get("host", "")) not in LOOPBACK_NAMES:
            return await _respond(writer, "403 Forbidden", b"this dashboard answers on loopback names only\n")
        path = target.split("?", 1)[0]
        if self.control is not None and path == "/playback" and method == "POST":
            return await self._playback(headers, reader, writer)
        if method not in ("GET", "HEAD"):
            return await _respond(writer, "405 Method Not Allowed", b"the dashboard is read-only\n", "Allow: GET, HEAD\r\n")
        if path == "/events" and method == "GET":
            return await self._stream_events(writer)
        asset = self.assets.get(path)
        if asset is None:
            return await _respond(writer, "404 Not Found", b"not found\n")
        body, content_type = asset
        await _respond(writer, "200 OK", body, content_type=content_type, head_only=method == "HEAD")

    async def _playback(self, headers: dict[str, str], reader: asyncio.StreamReader,
                        writer: asyncio.StreamWriter) -> None:
        assert self.control is not None
        origin = headers.get("origin")
        if origin is not None and origin.split("://", 1)[-1] != headers.get("host"):
            return await _respond(writer, "403 Forbidden", b"playback requests come from the dashboard's own page\n")
        if headers.get("content-type", "").split(";")[0].strip() != "application/json":
            return await _respond(writer, "415 Unsupported Media Type", b"send application/json\n")
        length = headers.get("content-length", "")
        if not length.isdigit() or int(length) > MAX_CONTROL_BODY:
            return await _respond(writer, "400 Bad Request", b"a playback request has a Content-Length up to 1 kB\n")
        body = await asyncio.wait_for(reader.readexactly(int(length)), REQUEST_TIMEOUT_S)
        try:
            request = json.loads(body)
            if not isinstance(request, dict):
                raise ValueError("a playback request is a JSON object")
            state = self.control(request)
        except ValueError as exc:  # json.JSONDecodeError and UnicodeDecodeError included
            return await _respond(writer, "400 Bad Request", f"{exc}\n".encode())
        await _respond(writer, "200 OK", json.dumps(state).encode(), content_type="application/json")

    async def _stream_events(self, writer: asyncio.StreamWriter) -> None:
        writer.write(("HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-store\r\n"
                      "Connection: keep-alive\r\n" + SECURITY_HEADERS + "\r\nretry: 1000\n\n").encode())
        browser = self.hub.attach()
        try:
            while not self._closing:
                await browser.wake.wait()
                writer.write("".join(f"data: {text}\n\n" for text in browser.take()).encode())
                await writer.drain()
        finally:
            self.hub.detach(browser)


async def _respond(writer: asyncio.StreamWriter, status: str, body: bytes, extra_headers: str = "",
                   content_type: str = "text/plain; charset=utf-8", head_only: bool = False) -> None:
    writer.write((f"HTTP/1.1 {status}\r\nContent-Type: {content_type}\r\nContent-Length: {len(body)}\r\n"
                  f"Cache-Control: no-cache\r\nConnection: close\r\n{SECURITY_HEADERS}{extra_headers}\r\n").encode())
    if not head_only:
        writer.write(body)
    await writer.drain()
