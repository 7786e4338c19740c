"""The trajectory reference: what a planned trajectory gives and what the outer loop tracks.

One type for both ends: :meth:`companion.control.trajectory.Trajectory.sample` returns it, the
mission's timeline warps it, and :class:`companion.control.outer_loop.OuterLoopController`
takes it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

Vec3 = Sequence[float]


@dataclass(frozen=True)
class Reference:
    """A trajectory reference in LOCAL_NED: position (m), velocity (m/s), acceleration (m/s^2), yaw
    (rad, [-pi, pi)) and yaw rate (rad/s).

    The vectors are 3 floats (a tuple or a (3,) array; the controller takes either) and the yaw
    floats; from ``Trajectory.sample_many`` they are (M, 3) and (M,) arrays. Left out: at rest
    (velocity and acceleration 0), facing north without turning.
    """

    position: Vec3 | np.ndarray
    velocity: Vec3 | np.ndarray = (0.0, 0.0, 0.0)
    acceleration: Vec3 | np.ndarray = (0.0, 0.0, 0.0)
    yaw_rad: float | np.ndarray = 0.0
    yaw_rate: float | np.ndarray = 0.0
