"""The generic outer loop: x, y (acceleration) and z (velocity) axes of one law, limited together.

Pure floats and numpy, no I/O. Frames: LOCAL_NED (x north, y east, z down; m, m/s, m/s^2).
:class:`OuterLoopController` takes a :class:`~companion.control.reference.Reference` and a
:class:`MeasuredState` and returns a :class:`ControlOutput`: acceleration references for x, y
and a velocity reference for z, in the autopilot's terms. The law of each axis, its integrator,
anti-windup and bumpless engage are the axis's (:class:`companion.control.rpt.RptAxis`); here
the horizontal limits act on the (x, y) vector (speed guard, acceleration norm, jerk with
braking first) and non-finite input gives the held safe output. The RPT controller
(:class:`companion.control.rpt.RptController`) and the PID baseline
(:class:`companion.control.pid.PidController`) are this loop with their own gains; the design,
the limits and how the output is sent to the autopilot are described in companion/control/rpt.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple, Protocol, Sequence

import numpy as np

from companion.control.reference import Reference, Vec3


CLIP = 1.0e6  # |error|, |velocity error|, |feed-forward|, |speed| beyond this are clipped (numerical safety)
INF = math.inf


class NonFiniteInput(ValueError):
    """A non-finite input arrived before any finite measurement: there is nothing to hold."""


def nonfinite(*values: float) -> bool:
    """True if any value is NaN or infinite (``x * 0.0`` is 0 exactly for finite ``x``)."""
    return sum(v * 0.0 for v in values) != 0.0


class MeasuredState(NamedTuple):
    """The estimate in LOCAL_NED; ``acceleration_ned`` (optional) is only used by ``engage``."""

    position_ned: Vec3
    velocity_ned: Vec3
    acceleration_ned: Vec3 | None = None


class ControlOutput(NamedTuple):
    """One step's output in the autopilot's terms (LOCAL_NED).

    ``acceleration_ned``: x, y acceleration references (m/s^2) and, in z, the rate of the z
    velocity reference (its feed-forward); ``velocity_ned_z``: the z velocity reference (m/s);
    ``position_ned`` / ``velocity_ned``: what to send with them under a position + velocity +
    acceleration type mask: the reference position (m) and the horizontal reference velocity
    with the z velocity reference (m/s); ``measured_position_ned`` / ``measured_velocity_ned``:
    the state the law saw; ``saturated``: per axis, a limit changed the law's output;
    ``valid``: False for the held safe output returned on non-finite input (then the position
    is the last finite measured one and the horizontal velocity 0: hold there).
    """

    acceleration_ned: tuple[float, float, float]
    velocity_ned_z: float
    position_ned: tuple[float, float, float]
    velocity_ned: tuple[float, float, float]
    measured_position_ned: tuple[float, float, float]
    measured_velocity_ned: tuple[float, float, float]
    saturated: tuple[bool, bool, bool]
    valid: bool = True

    def setpoint_fields(self) -> dict[str, np.ndarray]:
        """Keyword arguments for ``companion.mavlink.setpoints.Setpoint`` (mask 3072)."""
        return {"position_ned": np.array(self.position_ned), "velocity_ned": np.array(self.velocity_ned),
                "acceleration_ned": np.array(self.acceleration_ned)}

    def position_velocity_fields(self, vel_gain_xy: float = 2.0) -> dict[str, np.ndarray]:
        """``Setpoint`` keyword arguments for autopilots that take position + velocity but no
        acceleration targets (type_mask 3520, 2496 with yaw; ArduPilot Copter < 4.1 ignores 3072).

        The autopilot's velocity loop demands ``K_v (v_target - v)`` on top of its position
        correction, so the horizontal x, y acceleration reaches it as a velocity raised by
        ``a / K_v`` (``K_v``: ArduPilot ``PSC_VELXY_P``): through its P term, the same demand as
        type_mask 3072, filtered by PSC_ACC_XY_FILT; its I and D terms act on the raised velocity
        too, so this is an approximation of the feed-forward. z is unchanged (the z velocity
        reference). On the held safe output the velocity is the held one.
        """
        vx, vy, vz = self.velocity_ned
        ax, ay, _ = self.acceleration_ned if self.valid else (0.0, 0.0, 0.0)
        return {"position_ned": np.array(self.position_ned),
                "velocity_ned": np.array([vx + ax / vel_gain_xy, vy + ay / vel_gain_xy, vz])}


def position_only_target(output: ControlOutput, *, pos_gain_xy: float = 1.0, vel_gain_xy: float = 2.0,
                         pos_gain_z: float = 1.0, max_lead_m: float = 2.0) -> tuple[float, float, float]:
    """The position target to send when the autopilot only takes positions (mask 3576).

    The autopilot's own linear cascade is ``v_c = K_p (p_sp - p)``, ``a = K_v (v_c - v)``
    (ArduPilot ``PSC_POSXY_P``, ``PSC_VELXY_P``, ``PSC_POSZ_P``; PX4 ``MPC_XY_P``,
    ``MPC_XY_VEL_P_ACC``, ``MPC_Z_P``). Inverting it, the target that makes it demand the RPT
    output is ``p + (v + a / K_v) / K_p`` horizontally and ``p + v_z_ref / K_pz`` vertically.
    The lead (target - position) is limited to ``max_lead_m`` per axis group, because real
    autopilots leave the linear region (square-root controller) for large errors. Its
    integrators and the sampling of position targets make this an approximation of the RPT
    loop, not the RPT loop itself; prefer mask 3072 (:meth:`ControlOutput.setpoint_fields`).
    """
    px, py, pz = output.measured_position_ned
    vx, vy, _ = output.measured_velocity_ned
    ax, ay, _ = output.acceleration_ned
    lx = (vx + ax / vel_gain_xy) / pos_gain_xy
    ly = (vy + ay / vel_gain_xy) / pos_gain_xy
    lz = output.velocity_ned_z / pos_gain_z
    n = math.hypot(lx, ly)
    if n > max_lead_m:
        lx, ly = lx * max_lead_m / n, ly * max_lead_m / n
    lz = max(-max_lead_m, min(max_lead_m, lz))
    if not output.valid:  # held output: hold the last finite position
        lx = ly = lz = 0.0
    return (px + lx, py + ly, pz + lz)



def _vec(v: Vec3) -> Sequence[float]:
    return v.tolist() if isinstance(v, np.ndarray) else v



@dataclass(frozen=True)
class RptLimits:
    """Kinematic limits of the controller's output (``math.inf`` disables one).

    Horizontal limits act on the (x, y) vector norm; the speed guard caps the acceleration
    along the direction of motion at ``speed_gain * (speed_xy_mps - |v_xy|)`` (it brakes when
    above the limit) and at the jerk-limited braking curve ``sqrt(2 jerk (speed - |v|))``.
    The z velocity reference is bounded by ``climb_mps`` (up, negative z in NED) and
    ``descent_mps`` (down) and its rate by ``accel_z_mps2``. ``integral_*`` bound the integral
    term ``|c0 eta|`` (anti-windup clamp). ``max_dt_s``: a longer step (a stall) is integrated
    as this long. ``speed_gain`` and ``max_dt_s`` must be finite.
    """

    speed_xy_mps: float = 2.0
    accel_xy_mps2: float = 2.5
    jerk_xy_mps3: float = 5.0
    climb_mps: float = 1.0
    descent_mps: float = 0.8
    accel_z_mps2: float = 2.0
    speed_gain: float = 1.5  # 1/s
    integral_xy_mps2: float = 1.0
    integral_z_mps: float = 0.5
    max_dt_s: float = 0.5

    def __post_init__(self) -> None:
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if math.isnan(value) or value <= 0.0:
                raise ValueError(f"RptLimits.{name} must be > 0 (math.inf disables it), got {value!r}")
        for name in ("max_dt_s", "speed_gain"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"RptLimits.{name} must be finite")

    @classmethod
    def unlimited(cls) -> RptLimits:
        """No limits at all: the linear law (for pole checks and linear step responses)."""
        inf = math.inf
        return cls(inf, inf, inf, inf, inf, inf, 1.0, inf, inf, 0.5)


class Axis(Protocol):
    """One axis of a law as the outer loop drives it (:class:`companion.control.rpt.RptAxis`)."""

    anti_windup: bool
    valid: bool
    saturated: bool
    nonfinite_inputs: int
    feedforward: float
    _out: float  # the output last sent (the outer loop rescales x and y together)

    def reset(self) -> None: ...

    def engage(self, p_r: float, v_r: float, a_r: float, p: float, v: float,
               continuation: float | None = None) -> None: ...

    def step(self, dt: float, p_r: float, v_r: float, a_r: float, p: float, v: float) -> float: ...

    def commit(self, dt: float, u_lin: float, u_out: float) -> None: ...

    def hold(self, dt: float) -> float: ...


class OuterLoopController:
    """Three axes (x, y acceleration; z velocity) of one law, with the limits of ``limits``.

    The axes come from the subclass: :class:`companion.control.rpt.RptController` builds them
    from RPT parameters, the PID baseline (:class:`companion.control.pid.PidController`) from
    PID gains (both with :func:`companion.control.rpt.outer_loop_axes`). ``step`` auto-engages
    (continuation: hover, current vertical velocity) if :meth:`engage` was not called.
    """

    def __init__(self, x: Axis, y: Axis, z: Axis, limits: RptLimits) -> None:
        self.limits = limits
        self.x, self.y, self.z = x, y, z
        self.anti_windup = x.anti_windup
        self.engaged = False
        self.nonfinite_inputs = 0
        self._last_position: tuple[float, float, float] | None = None
        self._amax, self._jmax = limits.accel_xy_mps2, limits.jerk_xy_mps3
        self._vmax, self._ks, self._max_dt = limits.speed_xy_mps, limits.speed_gain, limits.max_dt_s

    def reset(self) -> None:
        for axis in (self.x, self.y, self.z):
            axis.reset()
        self.engaged = False

    def engage(self, measured: MeasuredState, reference: Reference,
               acceleration_ned: Vec3 | None = None) -> None:
        """Bumpless start: the first output continues the vehicle's current motion.

        The x, y continuation is ``acceleration_ned`` if given, else ``measured.acceleration_ned``
        if set, else 0 (hover); the z continuation is the measured vertical velocity. Each
        integrator is set so that the law outputs exactly that for these inputs (within the
        integral clamp) and the rate limiters start from it; with a reference that starts at
        the vehicle's state the integrators start near 0.
        """
        p = _vec(measured.position_ned)
        v = _vec(measured.velocity_ned)
        pr, vr, ar = _vec(reference.position), _vec(reference.velocity), _vec(reference.acceleration)
        acc = acceleration_ned if acceleration_ned is not None else measured.acceleration_ned
        acc = _vec(acc) if acc is not None else (0.0, 0.0, 0.0)
        if nonfinite(*p, *v, *pr, *vr, *ar, acc[0], acc[1]):
            raise NonFiniteInput("engage needs a finite measured state, reference and continuation")
        ax, ay = float(acc[0]), float(acc[1])
        n = math.hypot(ax, ay)
        if n > self._amax:
            ax, ay = ax * self._amax / n, ay * self._amax / n
        self.x.engage(pr[0], vr[0], ar[0], p[0], v[0], ax)
        self.y.engage(pr[1], vr[1], ar[1], p[1], v[1], ay)
        self.z.engage(pr[2], vr[2], ar[2], p[2], v[2], None)
        self._last_position = (float(p[0]), float(p[1]), float(p[2]))
        self.engaged = True

    def step(self, dt: float, reference: Reference, measured: MeasuredState) -> ControlOutput:
        """One control step (see :class:`ControlOutput`); non-finite input -> the held safe output."""
        prx, pry, prz = _vec(reference.position)
        vrx, vry, vrz = _vec(reference.velocity)
        arx, ary, arz = _vec(reference.acceleration)
        px, py, pz = _vec(measured.position_ned)
        vx, vy, vz = _vec(measured.velocity_ned)
        if (dt * 0.0 + prx * 0.0 + pry * 0.0 + prz * 0.0 + vrx * 0.0 + vry * 0.0 + vrz * 0.0 + arx * 0.0
                + ary * 0.0 + arz * 0.0 + px * 0.0 + py * 0.0 + pz * 0.0 + vx * 0.0 + vy * 0.0 + vz * 0.0) != 0.0:
            return self.held_output(dt)
        if dt <= 0.0:
            raise ValueError(f"dt must be > 0, got {dt!r}")
        if not self.engaged:
            self.engage(measured, reference)
        if dt > self._max_dt:
            dt = self._max_dt
        xa, ya = self.x, self.y
        ux_lin = xa.law(prx, vrx, arx, px, vx)
        uy_lin = ya.law(pry, vry, ary, py, vy)
        ux, uy = ux_lin, uy_lin
        # speed guard: cap the acceleration along the direction of motion
        vmax = self._vmax
        hx = hy = 0.0  # unit direction of motion while the guard bites
        if vmax < INF:
            cx = CLIP if vx > CLIP else (-CLIP if vx < -CLIP else vx)
            cy = CLIP if vy > CLIP else (-CLIP if vy < -CLIP else vy)
            sp = math.sqrt(cx * cx + cy * cy)
            if sp > 1e-6:
                room = vmax - sp
                cap = self._ks * room
                if room > 0.0:  # and no faster than the jerk limit can bring it back to 0
                    cap = min(cap, math.sqrt(2.0 * self._jmax * room))
                a_par = (ux * cx + uy * cy) / sp
                if a_par > cap:
                    k = (a_par - cap) / sp
                    ux -= k * cx
                    uy -= k * cy
                    hx, hy = cx / sp, cy / sp
        # acceleration norm
        amax = self._amax
        n = math.sqrt(ux * ux + uy * uy)
        if n > amax:
            s = amax / n
            ux *= s
            uy *= s
        # jerk: rate limiter on the acceleration vector
        ox, oy = xa._out, ya._out
        dx, dy = ux - ox, uy - oy
        r = self._jmax * dt
        n = math.sqrt(dx * dx + dy * dy)
        if n > r:
            if hx == 0.0 and hy == 0.0:
                s = r / n
                ux = ox + dx * s
                uy = oy + dy * s
            else:  # braking first: the change along the motion gets the jerk budget before the turn
                d_par = dx * hx + dy * hy
                d_par = r if d_par > r else (-r if d_par < -r else d_par)
                qx, qy = dx - (dx * hx + dy * hy) * hx, dy - (dx * hx + dy * hy) * hy
                q = math.sqrt(qx * qx + qy * qy)
                rest = math.sqrt(max(0.0, r * r - d_par * d_par))
                s = rest / q if q > rest else 1.0
                ux = ox + d_par * hx + qx * s
                uy = oy + d_par * hy + qy * s
        xa.commit(dt, ux_lin, ux)
        ya.commit(dt, uy_lin, uy)
        za = self.z
        wz = za.step(dt, prz, vrz, arz, pz, vz)
        self._last_position = (px, py, pz)
        return ControlOutput((ux, uy, za.feedforward), wz, (prx, pry, prz), (vrx, vry, wz), (px, py, pz),
                             (vx, vy, vz), (xa.saturated, ya.saturated, za.saturated), True)

    def held_output(self, dt: float) -> ControlOutput:
        """The held safe output (non-finite input): accelerations and z velocity ramp to 0 under
        their rate limits, hold the last finite position, integrators frozen, ``valid=False``."""
        if self._last_position is None:
            raise NonFiniteInput("non-finite input before any finite measurement: nothing to hold")
        self.nonfinite_inputs += 1
        if not (dt * 0.0 == 0.0) or dt <= 0.0:
            dt = 0.02
        dt = min(dt, self._max_dt)
        ox, oy = self.x._out, self.y._out
        n = math.hypot(ox, oy)
        r = self._jmax * dt
        s = max(0.0, n - r) / n if n > 0.0 else 0.0
        self.x._out, self.y._out = ox * s, oy * s
        for axis in (self.x, self.y):
            axis.valid = False
            axis.saturated = False
            axis.nonfinite_inputs += 1
        wz = self.z.hold(dt)
        return ControlOutput((ox * s, oy * s, self.z.feedforward), wz, self._last_position, (0.0, 0.0, wz),
                             self._last_position, (0.0, 0.0, 0.0), (False, False, False), False)
