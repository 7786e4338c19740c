"""The simulated copter as the MAVLink process (sitl/vehicle.py) drives it: truth, sensors,
the autopilot's own estimator and flight controller, stepped in lockstep at 400 Hz.

What it shares with the fixed wing (sensors, estimator, snapshots, commands) is
:class:`sitl.simulated_vehicle.SimulatedVehicle`; frames and units are described there.
"""

from __future__ import annotations

import math

import numpy as np

from companion.frames import GRAVITY_MPS2
from sitl.dynamics import AirframeParams, GaussianStream, QuadrotorDynamics, WindConfig
from sitl.flight_control import GUIDED, LAND, ControlLimits, FlightController
from sitl.simulated_vehicle import EstimateState, GpsSample, ImuSample, SimulatedVehicle, TruthState

__all__ = ["EstimateState", "GpsSample", "ImuSample", "SimulatedCopter", "TruthState", "WindConfig"]


class SimulatedCopter(SimulatedVehicle):
    """A quadrotor with an ArduPilot-Copter-like autopilot, stepped in simulation time.

    ``home`` is the geodetic anchor of the truth NED frame (lat deg, lon deg, alt m AMSL; the
    floor is at its altitude). ``position_source`` is EK3_SRC1_POSXY: "extnav" (vision from the
    companion; yaw too) or "gps". ``vision_delay_s`` plays VISO_DELAY_MS: it is subtracted from
    each vision sample's ``t_capture``. ``viso_pos_noise_m`` / ``viso_vel_noise_mps`` are the
    measurement-noise floors VISO_POS_M_NSE / VISO_VEL_M_NSE. ``limits`` overrides speeds,
    RTL_ALT, timeouts etc. of :class:`sitl.flight_control.ControlLimits`.
    """

    MAV_TYPE = 2  # MAV_TYPE_QUADROTOR

    def __init__(
        self,
        *,
        seed: int,
        home: tuple[float, float, float],
        gps_enabled: bool = True,
        position_source: str = "extnav",
        wind: WindConfig | None = None,
        start_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
        start_yaw_rad: float = 0.0,
        vision_delay_s: float = 0.01,
        viso_pos_noise_m: float = 0.2,
        viso_vel_noise_mps: float = 0.1,
        airframe: AirframeParams | None = None,
        limits: ControlLimits | None = None,
    ) -> None:
        streams = [GaussianStream(s) for s in np.random.SeedSequence(seed).spawn(6)]
        super().__init__(streams=streams, home=home, gps_enabled=gps_enabled, position_source=position_source,
                         start_yaw_rad=start_yaw_rad, vision_delay_s=vision_delay_s,
                         viso_pos_noise_m=viso_pos_noise_m, viso_vel_noise_mps=viso_vel_noise_mps)
        dyn = QuadrotorDynamics(noise=streams[0], airframe=airframe, wind=wind, start_ned=start_ned,
                                start_yaw_rad=start_yaw_rad)
        self._attach(dyn, FlightController(status=self._status, estimator=self._est, airframe=dyn.airframe,
                                           limits=limits))

    def _substep(self) -> None:
        imu = self._imu
        self._dyn.step(self._dt, self._fc.update(self.t, self._dt, (imu.gx, imu.gy, imu.gz)))
        self._sense()

    @property
    def guided(self) -> bool:
        """In GUIDED (position targets are flown)."""
        return self._fc.mode == GUIDED

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
