"""The MAVLink parameter protocol over the companion's link: read all, read one, write with read-back.

PARAM_VALUE carries every value in a float field. ArduPilot casts integers to float; PX4
copies their bytes (``Firmware.params_bytewise``): values are decoded and encoded accordingly,
so callers always see numbers. A write is PARAM_SET followed by the autopilot's PARAM_VALUE
echo; it is retried ``retries`` times and succeeds only when the echoed value is the one written
(a parameter the firmware clamps or refuses reads back different).
"""

from __future__ import annotations

import asyncio
import logging
import math
import struct
from collections.abc import Callable
from dataclasses import dataclass

from companion import clock
from companion.mavlink.firmware import Firmware
from companion.mavlink.link import MavlinkLink, mavlink

log = logging.getLogger("companion.params")

INT_TYPES = {mavlink.MAV_PARAM_TYPE_UINT8, mavlink.MAV_PARAM_TYPE_INT8, mavlink.MAV_PARAM_TYPE_UINT16,
             mavlink.MAV_PARAM_TYPE_INT16, mavlink.MAV_PARAM_TYPE_UINT32, mavlink.MAV_PARAM_TYPE_INT32}
LIST_IDLE_S = 1.0  # no PARAM_VALUE for this long during a list: ask for the missing ones by index


class ParamError(Exception):
    """A parameter could not be read or written."""


@dataclass(frozen=True)
class ParamValue:
    value: float
    param_type: int  # MAV_PARAM_TYPE


def decode(raw: float, param_type: int, bytewise: bool) -> float:
    """The number a PARAM_VALUE float field stands for."""
    if bytewise and param_type in INT_TYPES:
        return float(struct.unpack("<i", struct.pack("<f", raw))[0])
    return float(raw)


def encode(value: float, param_type: int, bytewise: bool) -> float:
    """The PARAM_SET float field for ``value``."""
    if bytewise and param_type in INT_TYPES:
        return struct.unpack("<f", struct.pack("<i", int(round(value))))[0]
    return float(value)


def same_value(a: float, b: float, param_type: int) -> bool:
    if param_type in INT_TYPES:
        return int(round(a)) == int(round(b))
    return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-6)  # float32 round trip


class ParameterClient:
    """Parameter reads and writes with the autopilot on ``link`` (answers come through its dispatch)."""

    def __init__(self, link: MavlinkLink, firmware: Callable[[], Firmware | None], timeout_s: float = 1.0,
                 retries: int = 3) -> None:
        self.link = link
        self.firmware = firmware
        self.timeout_s = timeout_s
        self.retries = retries
        self.values: dict[str, ParamValue] = {}
        self.count: int | None = None  # param_count the autopilot reports
        self._by_index: dict[int, str] = {}
        self._changed = asyncio.Event()
        link.subscribe("PARAM_VALUE", self._on_value)

    def _bytewise(self) -> bool:
        firmware = self.firmware()
        return firmware is not None and firmware.params_bytewise

    def _on_value(self, msg: mavlink.MAVLink_message) -> None:
        name = msg.param_id.rstrip("\x00")
        self.values[name] = ParamValue(decode(msg.param_value, msg.param_type, self._bytewise()), msg.param_type)
        self.count = msg.param_count
        if 0 <= msg.param_index < 0xFFFF:
            self._by_index[msg.param_index] = name
        self._changed.set()

    async def _wait_change(self, timeout_s: float) -> bool:
        """Until a PARAM_VALUE arrived since the last call (True) or ``timeout_s`` passed (False)."""
        try:
            await asyncio.wait_for(self._changed.wait(), timeout_s)
            return True
        except TimeoutError:
            return False
        finally:
            self._changed.clear()

    async def fetch_all(self, timeout_s: float = 60.0) -> dict[str, float]:
        """Every parameter (PARAM_REQUEST_LIST, then the missing indices one by one); ParamError if
        the list is not complete within ``timeout_s``."""
        target = self.link.target()
        self.link.send(mavlink.MAVLink_param_request_list_message(*target))
        deadline = clock.now() + timeout_s
        while self.count is None or len(self._by_index) < self.count:
            if clock.now() > deadline:
                have = len(self._by_index)
                raise ParamError(f"parameter list incomplete after {timeout_s:g} s ({have} of {self.count or '?'})")
            if not await self._wait_change(LIST_IDLE_S):
                if self.count is None:
                    self.link.send(mavlink.MAVLink_param_request_list_message(*target))
                    continue
                for index in [i for i in range(self.count) if i not in self._by_index][:20]:
                    self.link.send(mavlink.MAVLink_param_request_read_message(*target, b"", index))
        return {name: self.values[name].value for name in self._by_index.values()}

    async def read(self, name: str) -> float:
        """One parameter by name (PARAM_REQUEST_READ); ParamError if the autopilot does not answer."""
        for _ in range(self.retries):
            self.values.pop(name, None)
            self.link.send(mavlink.MAVLink_param_request_read_message(*self.link.target(), name.encode(), -1))
            deadline = clock.now() + self.timeout_s
            while name not in self.values and clock.now() < deadline:
                await self._wait_change(max(deadline - clock.now(), 0.0))
            if name in self.values:
                return self.values[name].value
        raise ParamError(f"{name}: no answer to PARAM_REQUEST_READ")

    async def write(self, name: str, value: float) -> float:
        """PARAM_SET ``name`` = ``value``; the value read back (ParamError unless it is ``value``)."""
        known = self.values.get(name)
        param_type = known.param_type if known is not None else mavlink.MAV_PARAM_TYPE_REAL32
        raw = encode(value, param_type, self._bytewise())
        for _ in range(self.retries):
            self.values.pop(name, None)
            self.link.send(mavlink.MAVLink_param_set_message(*self.link.target(), name.encode(), raw, param_type))
            deadline = clock.now() + self.timeout_s
            while name not in self.values and clock.now() < deadline:
                await self._wait_change(max(deadline - clock.now(), 0.0))
            echoed = self.values.get(name)
            if echoed is None:
                continue
            if same_value(echoed.value, value, param_type):
                return echoed.value
            raise ParamError(f"{name}: wrote {value:g}, the autopilot reads back {echoed.value:g}")
        raise ParamError(f"{name}: no PARAM_VALUE echo after {self.retries} PARAM_SET")
