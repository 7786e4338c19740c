"""Timings and response figures of the outer-loop controllers for ``companion bench``.

:func:`run_control_bench` times one 3-axis step of :class:`RptController` (and of the PID
baseline), wall-clock milliseconds per call on this machine, (median, p99) over ``repeat``
calls; the target is a median <= 0.05 ms in CPython (the hot path is plain floats).
:func:`control_figures` computes the step responses of the default gains per axis and the
RPT / PID tracking figures on the figure-eight; ``python -m companion.control.bench_control``
prints both.
"""

from __future__ import annotations

import time

import numpy as np

from companion.control.pid import PID_XY, PID_Z, PidAxis, PidController
from companion.control.response import (PAPER_MODEL, PAPER_XY, PAPER_Z, AxisPlant, FigureEight, PlantModel,
                                        compare_tracking, step_response)
from companion.timing import percentiles_ms
from companion.control.outer_loop import MeasuredState
from companion.control.reference import Reference
from companion.control.rpt import (ACCELERATION, VELOCITY, XY_PARAMS, Z_PARAMS, AxisLimits, RptAxis, RptController,
                                   RptLimits)

_STEP_DT_S = 0.02


def _time_controller(controller, repeat: int, as_arrays: bool) -> tuple[float, float]:
    """Step ``controller`` along a figure-eight (changing inputs, no branch cached)."""
    traj = FigureEight()
    n = 512
    refs, meas = [], []
    rng = np.random.default_rng(0)
    for k in range(n):
        r = traj.sample(k * _STEP_DT_S)
        noise = rng.normal(0.0, 0.01, 6)
        p = tuple(float(r.position[i] + noise[i]) for i in range(3))
        v = tuple(float(r.velocity[i] + noise[3 + i]) for i in range(3))
        if as_arrays:
            refs.append(Reference(np.array(r.position), np.array(r.velocity), np.array(r.acceleration)))
            meas.append(MeasuredState(np.array(p), np.array(v)))
        else:
            refs.append(r)
            meas.append(MeasuredState(p, v))
    controller.engage(meas[0], refs[0])
    step = controller.step
    for k in range(min(200, repeat)):  # warm-up
        step(_STEP_DT_S, refs[k % n], meas[k % n])
    samples = np.empty(repeat)
    clock = time.perf_counter
    for k in range(repeat):
        r, m = refs[k % n], meas[k % n]
        start = clock()
        step(_STEP_DT_S, r, m)
        samples[k] = clock() - start
    return percentiles_ms(samples)


def run_control_bench(repeat: int) -> dict[str, tuple[float, float]]:
    """Stage name -> (median ms, p99 ms) of one controller step (x, y, z) over ``repeat`` calls."""
    return {
        "control.rpt step (3 axes, tuples)": _time_controller(RptController(), repeat, False),
        "control.rpt step (3 axes, ndarray input)": _time_controller(RptController(), repeat, True),
        "control.pid step (3 axes, tuples)": _time_controller(PidController(), repeat, False),
    }


def control_figures() -> dict[str, object]:
    """Step responses (default gains; no limits unless named) and figure-eight tracking, RPT vs PID.

    Keys: ``step.<axis>.<plant>`` -> (rise s, settling s, overshoot %); ``tracking.<plant>`` ->
    {controller: (rms m, max m)}; ``tracking.<plant>.pid_over_rpt_rms`` -> the ratio.
    """
    free = RptLimits.unlimited()
    xy_lim = AxisLimits.from_limits(free, ACCELERATION)
    z_lim = AxisLimits.from_limits(free, VELOCITY)
    figures: dict[str, object] = {}
    for label, plant in (("ideal", PAPER_XY), ("lag 0.1 s", AxisPlant(ACCELERATION, 0.1))):
        figures[f"step.xy.{label}"] = tuple(step_response(RptAxis(XY_PARAMS, ACCELERATION, xy_lim), plant)[0])
    for label, plant in (("ideal", AxisPlant(VELOCITY, 0.0)), ("lag 0.1 s", PAPER_Z)):
        figures[f"step.z.{label}"] = tuple(step_response(RptAxis(Z_PARAMS, VELOCITY, z_lim), plant)[0])
    limited = RptLimits()
    figures["step.xy.ideal.default limits"] = tuple(step_response(
        RptAxis(XY_PARAMS, ACCELERATION, AxisLimits.from_limits(limited, ACCELERATION)), PAPER_XY)[0])
    figures["step.z.lag 0.1 s.default limits"] = tuple(step_response(
        RptAxis(Z_PARAMS, VELOCITY, AxisLimits.from_limits(limited, VELOCITY)), PAPER_Z)[0])
    # identical to RPT on a step (same poles, and a step has no velocity/acceleration to feed forward)
    figures["step.xy.ideal.pid"] = tuple(step_response(PidAxis(PID_XY, ACCELERATION, xy_lim), PAPER_XY)[0])
    figures["step.z.ideal.pid"] = tuple(step_response(PidAxis(PID_Z, VELOCITY, z_lim), AxisPlant(VELOCITY))[0])
    traj = FigureEight()
    for label, model in (("paper model (xy ideal, z lag 0.1 s)", PAPER_MODEL),
                         ("all axes lag 0.1 s", PlantModel(AxisPlant(ACCELERATION, 0.1), PAPER_Z))):
        res = compare_tracking(traj, model, {"rpt": RptController(), "pid": PidController()})
        figures[f"tracking.{label}"] = {k: tuple(v) for k, v in res.items()}
        figures[f"tracking.{label}.pid_over_rpt_rms"] = res["pid"].rms_m / res["rpt"].rms_m
    return figures


def main(repeat: int = 2000) -> int:
    print(f"{'stage':<50} {'median ms':>10} {'p99 ms':>10}")
    for name, (median, p99) in run_control_bench(repeat).items():
        print(f"{name:<50} {median:>10.4f} {p99:>10.4f}")
    print("1 m step responses (rise 10-90 % s, settling 2 % s, overshoot %), default gains:")
    figures = control_figures()
    for name, value in figures.items():
        if name.startswith("step."):
            print(f"  {name:<46} rise {value[0]:.2f}  settling {value[1]:.2f}  overshoot {value[2]:.1f}")
    print("figure-eight (2 m x 2 m, 20 s period, 0.3 m height wave, 2 laps), 3-D position error:")
    for name, value in figures.items():
        if name.startswith("tracking.") and isinstance(value, dict):
            row = "  ".join(f"{k} rms {v[0] * 1e3:.1f} mm max {v[1] * 1e3:.1f} mm" for k, v in value.items())
            print(f"  {name[9:]:<40} {row}  PID/RPT rms {figures[name + '.pid_over_rpt_rms']:.0f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
