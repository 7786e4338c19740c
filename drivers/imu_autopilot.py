"""The autopilot's IMU as a sensor: ``kind: imu, backend: autopilot``.

Every sample the autopilot streams (HIGHRES_IMU, or the SCALED_IMU / RAW_IMU the stream
negotiation chose: companion/mavlink/streams.py), converted to body FRD m/s^2 and rad/s and
stamped on the daemon clock by :class:`companion.mavlink.autopilot.AutopilotState`, with the
autopilot's newest attitude attached. Samples are queued between the link's dispatch and the
frontend (bounded: a stalled consumer loses the oldest, counted in ``samples.overflowed``); with no
sample for ``timeout_s`` the sensor is reported lost and reopened, like a device.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from companion.messages import ImuSample
from companion.plugins import register_backend
from companion.schema import meta
from drivers.base import Backend, PushedMessages

QUEUE_SAMPLES = 1000  # 2.5 s at 400 Hz: far more than one nav cycle


@dataclass
class AutopilotImuSettings:
    """``settings:`` of an imu with ``backend: autopilot``."""

    timeout_s: float = field(default=1.0, metadata=meta(
        "No sample for this long: the IMU stream is lost (reported, and waited for again).", (0.1, 10)))


class AutopilotImu(Backend[ImuSample]):
    """The IMU samples of ``state`` (an AutopilotState), every one, in order."""

    description = "autopilot IMU stream"

    def __init__(self, state: Any, settings: AutopilotImuSettings) -> None:
        self.state = state
        self.settings = settings
        self.samples: PushedMessages[ImuSample] = PushedMessages(QUEUE_SAMPLES)
        self._stop: Callable[[], None] | None = None

    async def open(self) -> None:
        self.samples.clear()
        self._stop = self.state.on_imu(self.samples.push)

    async def read(self) -> ImuSample:
        return await self.samples.get(self.settings.timeout_s, "IMU sample")

    async def close(self) -> None:
        if self._stop is not None:
            self._stop()
            self._stop = None


@register_backend("imu", "autopilot", AutopilotImuSettings)
def _autopilot_imu(name: str, settings: AutopilotImuSettings, ctx: Any) -> AutopilotImu:
    return AutopilotImu(ctx.autopilot, settings)
