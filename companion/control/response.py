"""Closed-loop responses of the outer loop on the paper's model (pure numpy, no I/O).

Plants (:class:`AxisPlant`), integrated exactly between control steps (zero-order hold):

* ``acceleration`` (x, y; eq. 12): the double integrator ``p'' = u + d``; with ``tau_s > 0``
  the achieved acceleration lags the reference, ``a' = (u - a) / tau``.
* ``velocity`` (z; eq. 17): the autopilot's vertical velocity loop. The paper models it as
  ideal (``p' = u``: eq. 17's single integrator, ``tau_s = 0``); with ``tau_s > 0`` it is the
  first-order loop ``v' = (u + d - v) / tau``. :data:`PAPER_Z` uses ``tau_s = 0.1`` s, an
  assumption (the paper only asks the outer loop to be much slower than the inner one: the
  fastest z pole is 2.1 rad/s against 10 rad/s).

``d`` is a constant or time-varying disturbance (an acceleration for x, y, a velocity bias for
z). Metrics: :func:`step_metrics` (rise 10-90 %, settling 2 %, overshoot), :func:`step_response`
for one axis, :func:`compare_tracking` for whole controllers on a 3-D trajectory (the
measurement is the true state, sampled at the control rate).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from companion.control.outer_loop import MeasuredState, OuterLoopController
from companion.control.reference import Reference
from companion.control.rpt import ACCELERATION, VELOCITY, RptAxis

CONTROL_DT_S = 0.02  # the 50 Hz nav loop


@dataclass(frozen=True)
class AxisPlant:
    """One axis of the vehicle as the outer loop sees it (see the module docstring)."""

    kind: str = ACCELERATION
    tau_s: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in (ACCELERATION, VELOCITY):
            raise ValueError(f"plant kind must be {ACCELERATION!r} or {VELOCITY!r}")
        if not (math.isfinite(self.tau_s) and self.tau_s >= 0.0):
            raise ValueError("tau_s must be finite and >= 0")


PAPER_XY = AxisPlant(ACCELERATION, 0.0)
PAPER_Z = AxisPlant(VELOCITY, 0.1)


@dataclass(frozen=True)
class PlantModel:
    """The three axes: x and y share ``xy``, z is ``z``."""

    xy: AxisPlant = field(default_factory=lambda: PAPER_XY)
    z: AxisPlant = field(default_factory=lambda: PAPER_Z)


PAPER_MODEL = PlantModel()


class AxisState:
    """Position, velocity and achieved acceleration of one simulated axis."""

    __slots__ = ("p", "v", "a")

    def __init__(self, p: float = 0.0, v: float = 0.0, a: float = 0.0) -> None:
        self.p, self.v, self.a = float(p), float(v), float(a)


def advance(plant: AxisPlant, s: AxisState, u: float, dt: float, d: float = 0.0) -> None:
    """Exact zero-order-hold propagation of ``s`` over ``dt`` with input ``u`` and disturbance ``d``."""
    tau = plant.tau_s
    if plant.kind == ACCELERATION:
        if tau == 0.0:
            acc = u + d
            s.p += s.v * dt + 0.5 * acc * dt * dt
            s.v += acc * dt
            s.a = u
            return
        x = math.exp(-dt / tau)
        a0 = s.a - u  # lagged part of the acceleration
        s.p += s.v * dt + 0.5 * (u + d) * dt * dt + a0 * tau * (dt - tau * (1.0 - x))
        s.v += (u + d) * dt + a0 * tau * (1.0 - x)
        s.a = u + a0 * x
        return
    target = u + d
    if tau == 0.0:
        s.p += target * dt
        s.a = (target - s.v) / dt
        s.v = target
        return
    x = math.exp(-dt / tau)
    v0 = s.v - target
    s.p += target * dt + v0 * tau * (1.0 - x)
    s.v = target + v0 * x
    s.a = -v0 * x / tau


# ------------------------------------------------------------------ one axis
class AxisRun(NamedTuple):
    """A simulated run of one axis, sampled at the control steps."""

    t: np.ndarray  # s
    position: np.ndarray  # m
    velocity: np.ndarray  # m/s
    output: np.ndarray  # the controller's output (m/s^2 or m/s)
    reference: np.ndarray  # reference position (m)


def simulate_axis(axis: RptAxis, plant: AxisPlant, reference: Callable[[float], tuple[float, float, float]],
                  duration_s: float, dt: float = CONTROL_DT_S, *, p0: float = 0.0, v0: float = 0.0,
                  disturbance: Callable[[float], float] | float = 0.0, engage: bool = True,
                  continuation: float | None = None) -> AxisRun:
    """Run ``axis`` on ``plant`` against ``reference(t) -> (p_r, v_r, a_r)`` from ``(p0, v0)``.

    With ``engage`` the axis is engaged at t = 0 with ``continuation`` (see :meth:`RptAxis.engage`).
    """
    n = int(round(duration_s / dt)) + 1
    t = np.arange(n) * dt
    pos, vel, out, ref = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    s = AxisState(p0, v0)
    dist = disturbance if callable(disturbance) else (lambda _t, c=float(disturbance): c)
    if engage:
        pr, vr, ar = reference(0.0)
        axis.engage(pr, vr, ar, s.p, s.v, continuation)
        s.a = axis.output if axis.kind == ACCELERATION else 0.0
    for k in range(n):
        tk = k * dt
        pr, vr, ar = reference(tk)
        u = axis.step(dt, pr, vr, ar, s.p, s.v)
        pos[k], vel[k], out[k], ref[k] = s.p, s.v, u, pr
        advance(plant, s, u, dt, dist(tk))
    return AxisRun(t, pos, vel, out, ref)


class StepMetrics(NamedTuple):
    rise_s: float  # 10 % -> 90 % of the final value
    settling_s: float  # last entry into the +-2 % band
    overshoot_pct: float  # peak beyond the final value, % of the step


def step_metrics(t: np.ndarray, y: np.ndarray, final: float = 1.0, start: float = 0.0,
                 band: float = 0.02) -> StepMetrics:
    """Rise time (10-90 %), settling time (``band``) and overshoot (%) of a step from ``start`` to ``final``."""
    span = final - start
    if span == 0.0:
        raise ValueError("a step needs final != start")
    x = (np.asarray(y, dtype=float) - start) / span  # normalised: 0 -> 1
    t = np.asarray(t, dtype=float)
    above10 = np.nonzero(x >= 0.1)[0]
    above90 = np.nonzero(x >= 0.9)[0]
    rise = float(t[above90[0]] - t[above10[0]]) if len(above90) and len(above10) else math.inf
    outside = np.nonzero(np.abs(x - 1.0) > band)[0]
    if len(outside) == 0:
        settling = 0.0
    elif outside[-1] == len(x) - 1:
        settling = math.inf
    else:
        settling = float(t[outside[-1] + 1] - t[0])
    overshoot = max(0.0, float(np.max(x)) - 1.0) * 100.0
    return StepMetrics(rise, settling, overshoot)


def step_response(axis: RptAxis, plant: AxisPlant | None = None, amplitude: float = 1.0,
                  duration_s: float = 40.0, dt: float = CONTROL_DT_S) -> tuple[StepMetrics, AxisRun]:
    """A unit (``amplitude``) step of the position reference at t = 0 from rest; metrics and run."""
    if plant is None:
        plant = PAPER_XY if axis.kind == ACCELERATION else AxisPlant(VELOCITY, 0.0)
    axis.reset()
    axis.engage(0.0, 0.0, 0.0, 0.0, 0.0)
    run = simulate_axis(axis, plant, lambda _t: (amplitude, 0.0, 0.0), duration_s, dt, engage=False)
    return step_metrics(run.t, run.position, amplitude), run


# ------------------------------------------------------------------ 3-D trajectories
class Trajectory:
    """A reference trajectory: ``sample(t) -> Reference`` over ``[0, duration_s]``.

    :func:`compare_tracking` also takes any object with ``sample(t) -> Reference`` and a
    ``duration_s`` or ``duration``, e.g. a planned :class:`companion.control.trajectory.Trajectory`.
    """

    duration_s: float

    def sample(self, t: float) -> Reference:  # pragma: no cover - interface
        raise NotImplementedError


@dataclass(frozen=True)
class FigureEight(Trajectory):
    """A smooth figure-eight (Gerono lemniscate) in LOCAL_NED, with an optional height wave.

    ``x = cx + a sin(w t)``, ``y = cy + (b/2) sin(2 w t)``, ``z = cz + h sin(w t)`` with
    ``w = 2 pi / period_s``; every derivative is analytic. Peak speed with the defaults
    (a 2 m, b 2 m, period 20 s, h 0.3 m): 0.89 m/s horizontally, peak horizontal acceleration
    0.42 m/s^2 (inside the default :class:`RptLimits`, so the comparison is of the laws).
    """

    center_ned: tuple[float, float, float] = (0.0, 0.0, -1.5)
    a_m: float = 2.0
    b_m: float = 2.0
    height_m: float = 0.3
    period_s: float = 20.0
    laps: float = 2.0

    @property
    def duration_s(self) -> float:  # type: ignore[override]
        return self.period_s * self.laps

    def sample(self, t: float) -> Reference:
        w = 2.0 * math.pi / self.period_s
        cx, cy, cz = self.center_ned
        s1, c1 = math.sin(w * t), math.cos(w * t)
        s2, c2 = math.sin(2 * w * t), math.cos(2 * w * t)
        a, hb, h = self.a_m, 0.5 * self.b_m, self.height_m
        return Reference((cx + a * s1, cy + hb * s2, cz + h * s1),
                         (a * w * c1, 2 * hb * w * c2, h * w * c1),
                         (-a * w * w * s1, -4 * hb * w * w * s2, -h * w * w * s1))


class TrackingError(NamedTuple):
    rms_m: float  # RMS of the 3-D position error over the run
    max_m: float


def simulate_tracking(trajectory: Trajectory, plant: PlantModel, controller: OuterLoopController,
                      dt: float = CONTROL_DT_S,
                      disturbance: Callable[[float], tuple[float, float, float]] | None = None) -> np.ndarray:
    """Fly ``controller`` along ``trajectory`` from its start state; returns the (n, 3) position errors."""
    ref0 = trajectory.sample(0.0)
    duration = getattr(trajectory, "duration_s", None)
    duration = float(trajectory.duration if duration is None else duration)  # type: ignore[attr-defined]
    states = [AxisState(ref0.position[i], ref0.velocity[i], ref0.acceleration[i]) for i in range(3)]
    if plant.z.kind == VELOCITY:
        states[2].a = ref0.acceleration[2]
    controller.reset()
    controller.engage(MeasuredState(ref0.position, ref0.velocity), ref0, acceleration_ned=ref0.acceleration)
    n = int(round(duration / dt)) + 1
    errors = np.empty((n, 3))
    plants = (plant.xy, plant.xy, plant.z)
    for k in range(n):
        t = k * dt
        ref = trajectory.sample(t)
        meas = MeasuredState((states[0].p, states[1].p, states[2].p), (states[0].v, states[1].v, states[2].v))
        out = controller.step(dt, ref, meas)
        errors[k] = [ref.position[i] - states[i].p for i in range(3)]
        d = disturbance(t) if disturbance is not None else (0.0, 0.0, 0.0)
        inputs = (out.acceleration_ned[0], out.acceleration_ned[1], out.velocity_ned_z)
        for i in range(3):
            advance(plants[i], states[i], inputs[i], dt, d[i])
    return errors


def compare_tracking(trajectory: Trajectory, plant: PlantModel,
                     controllers: Mapping[str, OuterLoopController], dt: float = CONTROL_DT_S,
                     disturbance: Callable[[float], tuple[float, float, float]] | None = None,
                     ) -> dict[str, TrackingError]:
    """``{name: (rms, max)}`` of the 3-D position error of each controller along ``trajectory``."""
    result = {}
    for name, controller in controllers.items():
        err = np.linalg.norm(simulate_tracking(trajectory, plant, controller, dt, disturbance), axis=1)
        result[name] = TrackingError(float(np.sqrt(np.mean(err**2))), float(np.max(err)))
    return result
