"""The simulated fixed wing as the MAVLink process (sitl/vehicle) drives it: a point mass with an
attitude (:mod:`sitl.fixedwing`), an ArduPlane-like autopilot (:mod:`sitl.plane_control`), the
shared sensors and estimator (:class:`sitl.simulated_vehicle.SimulatedVehicle`) plus a pitot
airspeed sensor, stepped at 400 Hz. Same interface as :class:`sitl.copter.SimulatedCopter`, with
ArduPlane custom_mode numbers. Frames and units as in :mod:`sitl.simulated_vehicle`.
"""

from __future__ import annotations

import math
from typing import Unpack

import numpy as np

from sitl.dynamics import WindConfig
from sitl.fixedwing import FixedWingDynamics, FixedWingParams
from sitl.plane_control import AUTO, PlaneController
from sitl.plane_guidance import PlaneLimits
from sitl.sensors import Airspeed
from sitl.simulated_vehicle import EstimateState, GpsSample, ImuSample, SensorOptions, SimulatedVehicle, TruthState

__all__ = ["EstimateState", "GpsSample", "ImuSample", "SimulatedPlane", "TruthState", "WindConfig"]


class SimulatedPlane(SimulatedVehicle):
    """A small fixed wing with an ArduPlane-like autopilot, stepped in simulation time.

    Arguments as :class:`sitl.copter.SimulatedCopter` (``position_source`` defaults to "gps":
    outdoors; no ``airframe``), plus ``start_airspeed_mps`` (0: on the runway at ``start_ned``;
    above 0, in level flight at that height and airspeed along ``start_yaw_rad``, already armed,
    in GUIDED loitering at the start height once an origin gives it a position), ``params``
    (airframe) and ``limits`` (autopilot).
    """

    MAV_TYPE = 1  # MAV_TYPE_FIXED_WING

    def __init__(
        self,
        *,
        seed: int,
        home: tuple[float, float, float],
        position_source: str = "gps",
        wind: WindConfig | None = None,
        start_ned: tuple[float, float, float] = (0.0, 0.0, 0.0),
        start_yaw_rad: float = 0.0,
        start_airspeed_mps: float = 0.0,
        params: FixedWingParams | None = None,
        limits: PlaneLimits | None = None,
        **sensors: Unpack[SensorOptions],
    ) -> None:
        super().__init__(seed=seed, stream_count=7, home=home, position_source=position_source,
                         start_yaw_rad=start_yaw_rad, **sensors)
        dyn = FixedWingDynamics(noise=self._streams[0], params=params, wind=wind, start_ned=start_ned,
                                start_yaw_rad=start_yaw_rad, start_airspeed_mps=start_airspeed_mps)
        self._airspeed = Airspeed(self._streams[6])
        self._last_throttle = 0.0
        self._attach(dyn, PlaneController(status=self._status, estimator=self._est, limits=limits))
        self._airspeed.sample(dyn.airspeed)
        if not dyn.on_ground:  # the autopilot was started in flight: its estimate starts at the truth
            for axis, position, velocity in zip(self._est.axes, dyn.position, dyn.velocity):
                axis.reset_position(float(position), 1.0)
                axis.reset_velocity(float(velocity), 0.1)
            self._fc.start_in_flight()

    def _substep(self) -> None:
        imu, dyn = self._imu, self._dyn
        command = self._fc.update(self.t, self._dt, (imu.gx, imu.gy, imu.gz), imu.ax, self._airspeed.airspeed_mps)
        self._last_throttle = command.throttle
        dyn.step(self._dt, command)
        self._airspeed.sample(dyn.airspeed)
        self._sense()

    # ------------------------------------------------------------------ fixed-wing specifics
    @property
    def landing(self) -> bool:
        """Flying the AUTO landing."""
        return self._fc.mode == AUTO and not self._fc.landed

    @property
    def airspeed_mps(self) -> float:
        """Latest pitot reading, m/s."""
        return self._airspeed.airspeed_mps

    @property
    def throttle_percent(self) -> float:
        """The autopilot's throttle output, %."""
        return 100.0 * self._last_throttle

    @property
    def aero(self) -> tuple[float, float, float, bool]:
        """Truth: (airspeed m/s, angle of attack rad, sideslip rad, stalled)."""
        d = self._dyn
        return d.airspeed, d.alpha, d.beta, d.stalled

    @property
    def wind_ned(self) -> np.ndarray:
        """Truth: the air velocity at the vehicle (mean + gust), NED m/s."""
        return self._dyn.wind_ned

    def set_rudder(self, yaw_rate_rad_s: float) -> None:
        """Fly uncoordinated: add a yaw-rate offset (rad/s) to the turn coordination (0 = coordinated)."""
        if not math.isfinite(yaw_rate_rad_s):
            self._nonfinite += 1
            return
        self._fc.rudder_rad_s = float(yaw_rate_rad_s)

    def land(self) -> tuple[bool, str]:
        """Land at home: the AUTO landing approach (:meth:`sitl.plane_control.PlaneController.land`)."""
        return self._fc.land()
