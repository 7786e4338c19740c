"""The timing every simulated sensor shares: captures on a fixed grid of the daemon clock.

Slot ``k`` is captured at ``t0 + k * period_s`` (``t0``: when the sensor was opened) and
delivered ``delay_s`` later (a scanner's sweep, a camera's exposure and transfer, a receiver's
latency). A reader more than a period late skips to the newest due slot, as a real device
that kept sampling would: nothing is queued up and delivered in a burst.
"""

from __future__ import annotations

import asyncio
import math


class CaptureGrid:
    """Slots every ``period_s`` seconds of the daemon clock from :meth:`start`."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self.t0 = 0.0  # daemon time of slot 0, s
        self._next = 0  # the next slot to deliver

    def start(self) -> None:
        """Slot 0 is now (call from the event loop, at open)."""
        self.t0 = asyncio.get_running_loop().time()
        self._next = 0

    async def next(self, delay_s: float) -> tuple[int, float]:
        """Wait until the next slot's data is due (its capture time + ``delay_s``); (slot, capture time s)."""
        loop = asyncio.get_running_loop()
        due = math.floor((loop.time() - delay_s - self.t0) / self.period_s)
        slot = max(self._next, due)  # more than a period late: skip to the newest due slot
        self._next = slot + 1
        t = self.t0 + slot * self.period_s
        await asyncio.sleep(max(0.0, t + delay_s - loop.time()))
        return slot, t
