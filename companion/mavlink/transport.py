"""Byte transports for the autopilot link: TCP, UDP and serial, opened and used without blocking.

pymavlink's ``mavutil`` connections connect TCP with a blocking ``connect()`` (a peer that never
accepts freezes the event loop), cannot tell a TCP end of file from "no data yet", and print to
stdout. The link therefore owns its sockets and file descriptors here and uses pymavlink only to
encode and parse MAVLink (``companion.mavlink.link``).

URLs use pymavlink's syntax:

- ``tcp:HOST:PORT``: connect to a TCP server (ArduPilot SITL, a telemetry bridge). The connect
  is asynchronous and bounded by a timeout; a dead peer is detected by TCP keepalive and
  ``TCP_USER_TIMEOUT`` (data unacknowledged for :data:`TCP_USER_TIMEOUT_S`), never by the
  autopilot merely being silent, so a paused autopilot keeps its connection.
- ``udpin:HOST:PORT`` (or ``udp:``): listen; replies go to the last sender.
- ``udpout:HOST:PORT``: send there; the socket is connected, so it is bound on the interface
  that reaches HOST (loopback for 127.0.0.1) and only hears that peer.
- ``/dev/ttyAMA0,921600`` (or just the device): a serial port, opened non-blocking.

:meth:`Transport.read` returns the bytes available now (``b""``: none) and raises
:class:`TransportClosed` when the peer closed or the device vanished; :meth:`Transport.write`
never blocks: bytes the kernel cannot take now are kept (at most :data:`MAX_PENDING_BYTES`) and
flushed first on the next write, a message that does not fit is dropped whole (never half a
frame) and counted in ``dropped_writes``.
"""

from __future__ import annotations

import asyncio
import errno
import ipaddress
import os
import socket
from dataclasses import dataclass

DEFAULT_BAUD = 921600
TCP_USER_TIMEOUT_S = 10.0  # unacknowledged data this long: the TCP peer is gone
TCP_KEEPALIVE_IDLE_S = 5
TCP_KEEPALIVE_INTERVAL_S = 2
TCP_KEEPALIVE_PROBES = 3
MAX_PENDING_BYTES = 65536
READ_CHUNK = 65536


class TransportClosed(Exception):
    """The peer closed the connection or the device went away: reopen."""


@dataclass(frozen=True)
class Endpoint:
    """A parsed link URL."""

    kind: str  # "tcp", "udpin", "udpout" or "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = DEFAULT_BAUD


def parse_url(url: str) -> Endpoint:
    """An :class:`Endpoint` from a pymavlink-style URL; ValueError names what is wrong."""
    scheme, sep, rest = url.partition(":")
    if sep and scheme in ("tcp", "udp", "udpin", "udpout"):
        host, _, port = rest.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"{url!r}: expected {scheme}:HOST:PORT")
        kind = {"udp": "udpin"}.get(scheme, scheme)
        return Endpoint(kind, host.strip("[]"), int(port))
    if url.startswith("/") or url.upper().startswith("COM"):
        device, _, baud = url.partition(",")
        if baud and not baud.isdigit():
            raise ValueError(f"{url!r}: expected DEVICE,BAUD")
        return Endpoint("serial", device=device, baud=int(baud) if baud else DEFAULT_BAUD)
    raise ValueError(f"{url!r}: expected tcp:HOST:PORT, udpin:HOST:PORT, udpout:HOST:PORT or /dev/DEVICE[,BAUD]")


async def _resolve(host: str, port: int, kind: socket.SocketKind) -> tuple[int, tuple]:
    """(family, address) for ``host``; literal addresses are not looked up (no thread, no delay).
    A name is looked up on asyncio's resolver thread: give addresses, not names, on a vehicle
    (a resolver that hangs would also hold the process at exit)."""
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        infos = await asyncio.get_running_loop().getaddrinfo(host, port, type=kind)
        family, _, _, _, address = infos[0]
        return family, address
    return (socket.AF_INET6, (host, port, 0, 0)) if ip.version == 6 else (socket.AF_INET, (host, port))


class Transport:
    """A non-blocking byte stream over one file descriptor (see the module docstring)."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.dropped_writes = 0
        self._pending = b""

    @property
    def fd(self) -> int:
        raise NotImplementedError

    def read(self) -> bytes:
        raise NotImplementedError

    def _send(self, data: bytes) -> int:
        """Write what the kernel takes now; the number of bytes written."""
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError

    def write(self, data: bytes) -> None:
        """Queue ``data`` (one whole message) without blocking; see the module docstring."""
        if self._pending:
            self._pending = self._pending[self._try_send(self._pending):]
        if self._pending and len(self._pending) + len(data) > MAX_PENDING_BYTES:
            self.dropped_writes += 1
            return
        if self._pending:
            self._pending += data
            return
        sent = self._try_send(data)
        self._pending = data[sent:]

    def _try_send(self, data: bytes) -> int:
        try:
            return self._send(data)
        except (BlockingIOError, InterruptedError):
            return 0


class StreamTransport(Transport):
    """TCP socket or serial device: a byte stream that can end."""

    def __init__(self, endpoint: Endpoint, fd: int, owner: object) -> None:
        super().__init__(endpoint)
        self._fd = fd
        self._owner = owner  # the socket or serial.Serial keeping the descriptor open

    @property
    def fd(self) -> int:
        return self._fd

    def read(self) -> bytes:
        try:
            data = os.read(self._fd, READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            raise TransportClosed(f"read failed: {exc.strerror or exc}") from exc
        if not data:  # readable with nothing to read: end of file, or the device vanished
            raise TransportClosed("closed by the peer" if self.endpoint.kind == "tcp" else "device gone")
        return data

    def _send(self, data: bytes) -> int:
        try:
            return os.write(self._fd, data)
        except (BlockingIOError, InterruptedError):
            raise
        except OSError as exc:
            raise TransportClosed(f"write failed: {exc.strerror or exc}") from exc

    def close(self) -> None:
        self._owner.close()  # type: ignore[attr-defined]


class DatagramTransport(Transport):
    """UDP: udpin answers the last sender; udpout talks to its one peer."""

    def __init__(self, endpoint: Endpoint, sock: socket.socket) -> None:
        super().__init__(endpoint)
        self._sock = sock
        self._peer: tuple | None = None  # udpin: the last sender

    @property
    def fd(self) -> int:
        return self._sock.fileno()

    def read(self) -> bytes:
        chunks = []
        while True:
            try:
                data, peer = self._sock.recvfrom(READ_CHUNK)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # ICMP port unreachable (nobody listens yet), network down: UDP carries on
                break
            self._peer = peer
            chunks.append(data)
        return b"".join(chunks)

    def _send(self, data: bytes) -> int:
        if self.endpoint.kind == "udpin" and self._peer is None:  # nobody has spoken yet
            return len(data)
        try:
            return self._sock.send(data) if self.endpoint.kind == "udpout" else self._sock.sendto(data, self._peer)
        except (BlockingIOError, InterruptedError):
            raise
        except OSError:  # peer not listening, network unreachable, no buffer space: this datagram is lost
            self.dropped_writes += 1
            return len(data)

    def close(self) -> None:
        self._sock.close()


def _tune_tcp(sock: socket.socket) -> None:
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_KEEPALIVE, 1)
    for option, value in (("TCP_KEEPIDLE", TCP_KEEPALIVE_IDLE_S), ("TCP_KEEPINTVL", TCP_KEEPALIVE_INTERVAL_S),
                          ("TCP_KEEPCNT", TCP_KEEPALIVE_PROBES),
                          ("TCP_USER_TIMEOUT", int(TCP_USER_TIMEOUT_S * 1000))):
        if hasattr(socket, option):  # Linux has all of them
            sock.setsockopt(socket.IPPROTO_TCP, getattr(socket, option), value)


async def open_transport(url: str, connect_timeout_s: float) -> Transport:
    """Open ``url`` without blocking the event loop; OSError / ValueError / TimeoutError on failure."""
    endpoint = parse_url(url)
    if endpoint.kind == "tcp":
        family, address = await asyncio.wait_for(_resolve(endpoint.host, endpoint.port, socket.SOCK_STREAM),
                                                 connect_timeout_s)
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setblocking(False)
        try:
            await asyncio.wait_for(asyncio.get_running_loop().sock_connect(sock, address), connect_timeout_s)
        except BaseException:
            sock.close()
            raise
        _tune_tcp(sock)
        return StreamTransport(endpoint, sock.fileno(), sock)
    if endpoint.kind in ("udpin", "udpout"):
        family, address = await asyncio.wait_for(_resolve(endpoint.host, endpoint.port, socket.SOCK_DGRAM),
                                                 connect_timeout_s)
        sock = socket.socket(family, socket.SOCK_DGRAM)
        sock.setblocking(False)
        try:
            if endpoint.kind == "udpin":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind(address)
            else:
                sock.connect(address)  # binds to the interface that reaches the peer
        except BaseException:
            sock.close()
            raise
        return DatagramTransport(endpoint, sock)
    return _open_serial(endpoint)


def _open_serial(endpoint: Endpoint) -> Transport:
    import serial  # pyserial: opens the device and sets the line up (raw, baud)

    try:
        # timeout=None sets VMIN=1: once the descriptor is non-blocking, "no data" is EAGAIN and an
        # empty read can only mean the device hung up (VMIN=0 would return empty reads either way).
        port = serial.Serial(endpoint.device, endpoint.baud, timeout=None, write_timeout=0, exclusive=True)
    except serial.SerialException as exc:
        raise OSError(errno.ENODEV, str(exc)) from exc
    os.set_blocking(port.fileno(), False)
    return StreamTransport(endpoint, port.fileno(), port)
