"""The simulated copter as the MAVLink process (sitl/vehicle.py) drives it: truth, sensors,
the autopilot's own estimator and flight controller, stepped in lockstep at 400 Hz.

What it shares with the fixed wing (sensors, estimator, snapshots, commands) is
:class:`sitl.simulated_vehicle.SimulatedVehicle`; frames and units are described there.
"""

from __future__ import annotations

import math
from typing import Unpack

from companion.frames import GRAVITY_MPS2
from sitl.dynamics import AirframeParams, QuadrotorDynamics, WindConfig
from sitl.flight_control import LAND, ControlLimits, FlightController
from sitl.simulated_vehicle import EstimateState, GpsSample, ImuSample, SensorOptions, SimulatedVehicle, TruthState

__all__ = ["EstimateState", "GpsSample", "ImuSample", "SimulatedCopter", "TruthState", "WindConfig"]


class SimulatedCopter(SimulatedVehicle):
    """A quadrotor with an ArduPilot-Copter-like autopilot, stepped in simulation time.

    ``seed``, ``home``, ``position_source`` (default "extnav": vision from the companion) and the
    :class:`sitl.simulated_vehicle.SensorOptions` as :class:`sitl.simulated_vehicle.SimulatedVehicle`;
    ``wind``, ``start_ned`` (m) and ``start_yaw_rad`` set the airframe's air and start pose,
    ``airframe`` its physics; ``limits`` overrides speeds, RTL_ALT, timeouts etc. of
    :class:`sitl.flight_control.ControlLimits`.
    """

    MAV_TYPE = 2  # MAV_TYPE_QUADROTOR

    def __init__(
        self,
        *,
        seed: int,
        home: tuple[float, float, float],
        position_source: str = "extnav",
        wind: WindConfig | None = None,
        start_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
        start_yaw_rad: float = 0.0,
        airframe: AirframeParams | None = None,
        limits: ControlLimits | None = None,
        **sensors: Unpack[SensorOptions],
    ) -> None:
        super().__init__(seed=seed, stream_count=6, home=home, position_source=position_source,
                         start_yaw_rad=start_yaw_rad, **sensors)
        dyn = QuadrotorDynamics(noise=self._streams[0], airframe=airframe, wind=wind, start_ned=start_ned,
                                start_yaw_rad=start_yaw_rad)
        self._attach(dyn, FlightController(status=self._status, estimator=self._est, airframe=dyn.airframe,
                                           limits=limits))

    def _substep(self) -> None:
        imu = self._imu
        self._dyn.step(self._dt, self._fc.update(self.t, self._dt, (imu.gx, imu.gy, imu.gz)))
        self._sense()

    @property
    def landing(self) -> bool:
        """In LAND."""
        return self._fc.mode == LAND

    @property
    def airspeed_mps(self) -> float:
        """What it reports as airspeed without a pitot: the estimated horizontal speed, m/s."""
        n, e, _ = self._est.axes
        return math.hypot(n.v, e.v)

    @property
    def throttle_percent(self) -> float:
        """Collective thrust as a percentage, 50 at hover (from the true vertical specific force)."""
        return 50.0 * -self._dyn.fz / GRAVITY_MPS2

    def land(self) -> tuple[bool, str]:
        """Switch to LAND."""
        return self._fc.set_mode(LAND)
