"""A serial port read without blocking the event loop: pyserial configures the port, the loop
watches its file descriptor (``loop.add_reader``) and hands each chunk read to the owner.

Shared by the serial backends (the Hokuyo SCIP link, the NMEA receiver). A read error or end of
file (the device was unplugged) stops the watching and reports :class:`DeviceLost` once.
"""

from __future__ import annotations

import asyncio
import os
from collections.abc import Callable

import serial

from drivers.base import DeviceLost


class SerialFd:
    """An open serial port whose fd the event loop watches: ``on_data(chunk)`` for what arrives,
    ``on_lost(error)`` once when the port fails or closes."""

    def __init__(self, port: serial.SerialBase, what: str, on_data: Callable[[bytes], None],
                 on_lost: Callable[[DeviceLost], None], read_bytes: int = 4096) -> None:
        """``what`` names the device in the errors (e.g. "scanner"); ``port.fileno()`` must work."""
        self.port = port
        self.fd = port.fileno()
        self._what = what
        self._on_data = on_data
        self._on_lost = on_lost
        self._read_bytes = read_bytes
        self._loop = asyncio.get_running_loop()
        self._loop.add_reader(self.fd, self._on_readable)

    @staticmethod
    async def open_port(url: str, baud: int) -> serial.SerialBase:
        """The port at ``url`` (a device path or a pyserial URL), opened off the event loop,
        non-blocking and exclusive; pyserial's SerialException (an OSError) if it is not there."""
        return await asyncio.to_thread(serial.serial_for_url, url, baudrate=baud, timeout=0, write_timeout=0,
                                       exclusive=True)

    def _on_readable(self) -> None:
        try:
            data = os.read(self.fd, self._read_bytes)
        except BlockingIOError:
            return
        except OSError as exc:
            return self._lost(DeviceLost(f"serial read failed: {exc}"))
        if not data:
            return self._lost(DeviceLost(f"serial port closed ({self._what} unplugged?)"))
        self._on_data(data)

    def _lost(self, error: DeviceLost) -> None:
        self._loop.remove_reader(self.fd)
        self._on_lost(error)

    def write(self, data: bytes) -> None:
        """Write all of ``data`` now; DeviceLost if the port fails or cannot take it at once."""
        try:
            written = os.write(self.fd, data)
        except OSError as exc:
            raise DeviceLost(f"serial write failed: {exc}") from exc
        if written != len(data):
            raise DeviceLost("serial output stalled")

    def close(self) -> None:
        self._loop.remove_reader(self.fd)
        self.port.close()
