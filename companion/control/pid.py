"""A plain PID position loop: the baseline the RPT controller is compared with.

Same interface, outputs, limits, anti-windup, bumpless engage and non-finite handling as
:class:`companion.control.rpt.RptController` (it runs the same :class:`RptAxis` machinery);
only the law differs. Per axis, with ``e = p_r - p`` and ``eta`` the integral of ``e``:

    x, y (acceleration output): u = k_p e - k_d v + k_i eta     (P on position, D on the measured
                                                                 velocity, I on the position error)
    z    (velocity output):     u = k_p e + k_i eta              (PI; a D term on a velocity output
                                                                 would feed the inner loop's own
                                                                 output back algebraically)

What makes it "plain": it sees the reference position only. No velocity or acceleration
feed-forward from the trajectory, and the derivative acts on the measurement (no derivative
kick on steps), which is how a hand-tuned PID position loop is usually built.

Gains: chosen to give the SAME bandwidth as the RPT defaults, in the strongest sense: the same
closed-loop poles. On the double integrator the PID's regulation loop has the characteristic
polynomial ``s^3 + k_d s^2 + k_p s + k_i`` (z: ``s^2 + k_p s + k_i`` on the single
integrator), so :meth:`PidGains.matching` takes ``k_p = c1``, ``k_d = c2``, ``k_i = c0`` of the
RPT law (eq. 16's polynomial). Defaults: x, y k_p 1.330 s^-2, k_d 1.650 s^-1, k_i 0.245 s^-3;
z k_p 2.236 s^-1, k_i 0.3125 s^-2. Disturbance rejection and the response to initial errors
are therefore identical; any difference in tracking comes from how the reference enters,
which is the RPT argument. (Both reach zero steady-state error to steps and ramps; only RPT
is exact on curved trajectories.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from companion.control.outer_loop import OuterLoopController
from companion.control.rpt import (ACCELERATION, VELOCITY, XY_PARAMS, Z_PARAMS, AxisLimits, RptAxis, RptGains,
                                   RptLimits, RptParams, outer_loop_axes)


@dataclass(frozen=True)
class PidGains:
    """PID gains of one axis: ``k_p`` (1/s^2 or 1/s), ``k_i`` (1/s^3 or 1/s^2), ``k_d`` (1/s; 0 for z)."""

    k_p: float
    k_i: float
    k_d: float = 0.0

    def __post_init__(self) -> None:
        for name in ("k_p", "k_i", "k_d"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"PidGains.{name} must be finite and >= 0, got {value!r}")

    @classmethod
    def matching(cls, params: RptParams, kind: str = ACCELERATION) -> PidGains:
        """The PID with the same closed-loop poles as the RPT law of ``params`` (same bandwidth)."""
        g = params.gains(kind)
        return cls(k_p=g.k_p, k_i=g.k_int, k_d=g.k_d if kind == ACCELERATION else 0.0)

    def axis_gains(self, kind: str = ACCELERATION) -> RptGains:
        """As the generic law: no feed-forward, derivative on the measured velocity."""
        return RptGains(k_int=self.k_i, k_p=self.k_p, k_d=self.k_d if kind == ACCELERATION else 0.0,
                        velocity_ff=0.0, acceleration_ff=0.0)


PID_XY = PidGains.matching(XY_PARAMS, ACCELERATION)
PID_Z = PidGains.matching(Z_PARAMS, VELOCITY)


class PidAxis(RptAxis):
    """One PID channel (same API as :class:`RptAxis`)."""

    __slots__ = ()

    def __init__(self, gains: PidGains = PID_XY, kind: str = ACCELERATION, limits: AxisLimits | None = None,
                 anti_windup: bool = True) -> None:
        super().__init__(gains.axis_gains(kind), kind, limits, anti_windup)


class PidController(OuterLoopController):
    """x, y, z PID with :class:`RptController`'s interface: ``step(dt, reference, measured)``."""

    def __init__(self, xy: PidGains = PID_XY, z: PidGains = PID_Z, limits: RptLimits | None = None,
                 anti_windup: bool = True) -> None:
        self.xy_gains = xy
        self.z_gains = z
        limits = limits if limits is not None else RptLimits()
        super().__init__(*outer_loop_axes(xy.axis_gains(ACCELERATION), z.axis_gains(VELOCITY), limits, anti_windup),
                         limits)
