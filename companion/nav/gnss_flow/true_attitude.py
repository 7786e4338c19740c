"""The true attitude from the pseudo-attitude and the flow's focus of expansion (the seed's
"pseudo pitch plus the pitch offset normal to the roll, pseudo yaw plus the yaw offset tangential
to it", done exactly), its covariance, and the rate error a derotation missed (the spin about
the direction of travel of the GNSS-derived rates, a gyro's bias and noise), from the flow.

Frames: world LOCAL_NED, body FRD, the camera's optical frame (companion/calibration.py) placed in
the body by ``cam_to_body``; normalised image coordinates; Euler angles ZYX rad.
"""

from __future__ import annotations

import math

import numpy as np

from companion.frames import euler_from_rotation, rotation_from_euler, wrap_pi
from companion.nav.gnss_flow.flow import FocusOfExpansion, derotate, velocity_offsets
from companion.nav.gnss_flow.pseudo_attitude import PseudoAttitude

JACOBIAN_STEP = 1e-6  # central-difference step of the attitude covariance, rad and normalised units


def true_euler(pseudo_rad: np.ndarray, foe_n: np.ndarray, forward: float, cam_to_body: np.ndarray,
               along_over_normal: float = 0.0) -> tuple[np.ndarray, tuple[float, float]]:
    """(roll, pitch, yaw) rad of body FRD in NED, and the (pitch offset, drift angle) rad, from the
    pseudo Euler angles ``pseudo_rad`` (3,) (the frame whose x is the velocity and whose -z the
    normal specific force), the focus of expansion ``foe_n`` (2,) (normalised coordinates of the
    camera ``cam_to_body``; ``forward`` +1 when the flow expands from it, -1 when it converges) and
    the specific force's ``along_over_normal`` (:class:`.pseudo_attitude.PseudoAttitude`).

    The velocity in the body is ``(cos a cos b, sin b, sin a cos b)`` (a the pitch offset, b the
    drift angle, :func:`.flow.velocity_offsets`), so body = pseudo frame turned by the
    wind-to-body rotation (:func:`wind_to_body`): ``R_nb = R_nw C_bw^T``. Coordinated flight
    keeps the specific force in the body's x-z plane, but the pseudo frame holds only its part
    normal to the (ground) velocity: turned by the offsets alone, a body crabbing by b would feel
    the along-track part times sin b sideways. So the pseudo frame is first rolled about the
    velocity by ``asin(tan b * along_over_normal)`` (in the SITL Table 1 flight 0.5 deg, descending
    with 7 deg of crab; 0.2 deg RMS over its wings-level flight). Level and wings level this is
    pitch = flight path + a, yaw = course - b."""
    direction = forward * np.append(foe_n, 1.0) / math.hypot(foe_n[0], foe_n[1], 1.0)
    a, b = velocity_offsets(direction, cam_to_body)
    roll, pitch, yaw = (float(x) for x in pseudo_rad)
    roll += crab_roll(b, along_over_normal)
    return turned_by_offsets(roll, pitch, yaw, a, b), (a, b)


def turned_by_offsets(roll: float, pitch: float, yaw: float, pitch_offset: float, drift: float) -> np.ndarray:
    """(roll, pitch, yaw) rad of the body whose velocity lies at ``pitch_offset`` below its nose and
    ``drift`` to its right (rad), for a frame with x along the velocity at Euler angles ``roll``,
    ``pitch``, ``yaw`` (rad, ZYX, in NED): ``R_nb = R_nw C_bw^T`` (:func:`wind_to_body`)."""
    return np.array(euler_from_rotation(rotation_from_euler(roll, pitch, yaw) @ wind_to_body(pitch_offset, drift).T))


def crab_roll(drift: float, along_over_normal: float) -> float:
    """The roll (rad) about the velocity that keeps a body crabbing by ``drift`` (rad) free of
    lateral specific force: ``asin(tan(drift) * along_over_normal)`` (:func:`true_euler`)."""
    return math.asin(max(-1.0, min(1.0, math.tan(drift) * along_over_normal)))


def wind_to_body(pitch_offset: float, drift: float) -> np.ndarray:
    """``C_bw`` (3x3, ``v_body = C_bw @ v_wind``) for the velocity at ``pitch_offset`` (a) below
    the nose and ``drift`` (b) to its right, both rad: ``R_y(-a) R_z(b)`` (aerodynamic convention),
    whose first column is the velocity's direction in the body ``(cos a cos b, sin b, sin a cos b)``."""
    ca, sa, cb, sb = math.cos(pitch_offset), math.sin(pitch_offset), math.cos(drift), math.sin(drift)
    return np.array([[ca * cb, -ca * sb, -sa], [sb, cb, 0.0], [sa * cb, -sa * sb, ca]])


def true_euler_covariance(pseudo: PseudoAttitude, foe: FocusOfExpansion, forward: float,
                          cam_to_body: np.ndarray) -> np.ndarray:
    """(3, 3) rad^2: the pseudo-attitude's and the FOE's covariances (independent) through a
    central-difference Jacobian of :func:`true_euler`."""
    x = np.array([pseudo.roll, pseudo.pitch, pseudo.yaw, *foe.point_n])
    cov_in = np.zeros((5, 5))
    cov_in[:3, :3] = pseudo.covariance
    cov_in[3:, 3:] = foe.covariance_n
    jacobian = np.zeros((3, 5))
    for i in range(5):
        dx = np.zeros(5)
        dx[i] = JACOBIAN_STEP
        plus = true_euler(x[:3] + dx[:3], x[3:] + dx[3:], forward, cam_to_body, pseudo.along_over_normal)[0]
        minus = true_euler(x[:3] - dx[:3], x[3:] - dx[3:], forward, cam_to_body, pseudo.along_over_normal)[0]
        jacobian[:, i] = [wrap_pi(float(d)) / (2 * JACOBIAN_STEP) for d in plus - minus]
    cov = jacobian @ cov_in @ jacobian.T
    return 0.5 * (cov + cov.T)


def rotation_correction(points_n: np.ndarray, flows_n: np.ndarray, translational: np.ndarray,
                        foe: FocusOfExpansion, rates: np.ndarray, dt: float, cam_to_body: np.ndarray,
                        axes: np.ndarray, prior_sigma_rad_s: float | None = None) -> np.ndarray:
    """The body rates (body FRD rad/s, (3,)) that the derotation by ``rates`` (body FRD rad/s over
    ``dt`` s) missed along ``axes`` ((k, 3) unit vectors, body FRD), from the flow itself.

    A rate error adds flow that does not depend on depth, so it turns the far ground's short flow
    lines much more than the near ground's long ones, where a shift of the FOE turns the near lines
    most: the two are told apart by the spread of depths. About the direction of travel the flow
    lines spiral; about the other axes they bend away from the FOE (a yaw-rate error of 1 mrad/s
    moves a 100 m high, 17 m/s FOE by about a degree). Linearised weighted least squares on the
    sines of the FOE's inliers' angles to their lines from it (each of its 1-sigma
    ``foe.sine_sigma``), for the rate errors and the FOE's shift together (the shift is left to the
    next :func:`.flow.focus_of_expansion`). ``prior_sigma_rad_s``: each axis's error is a priori
    zero with this 1-sigma (a gyro's bias and noise over the pair), so what the flow cannot tell
    stays the gyro's; None: no prior (GNSS-derived rates about the direction of travel).
    ``points_n``, ``flows_n`` and ``translational`` (its derotation by ``rates``) (N, 2)
    normalised; the camera ``cam_to_body``."""
    inl = foe.inliers
    points, flows = points_n[inl], translational[inl]

    def sines(foe_n: np.ndarray, flow: np.ndarray) -> np.ndarray:
        radial = points - foe_n
        cross = radial[:, 0] * flow[:, 1] - radial[:, 1] * flow[:, 0]
        return cross / (np.linalg.norm(radial, axis=1) * np.linalg.norm(flows, axis=1))

    step = 1e-3  # rad/s and normalised units: the sines are linear in both to well below this
    axes = np.atleast_2d(np.asarray(axes, dtype=float))
    base = sines(foe.point_n, flows)
    columns = [sines(foe.point_n, derotate(points, flows_n[inl], rates + step * axis, dt, cam_to_body)) - base
               for axis in axes]
    columns += [sines(foe.point_n + d, flows) - base for d in np.eye(2) * step]
    weight = 1.0 / np.maximum(foe.sine_sigma[inl], 1e-9)
    jacobian, target = np.column_stack(columns) * (weight / step)[:, None], -base * weight
    if prior_sigma_rad_s is not None:
        prior = np.zeros((len(axes), len(columns)))
        prior[:, :len(axes)] = np.eye(len(axes)) / prior_sigma_rad_s
        jacobian, target = np.vstack((jacobian, prior)), np.concatenate((target, np.zeros(len(axes))))
    solution, *_ = np.linalg.lstsq(jacobian, target, rcond=None)
    return solution[:len(axes)] @ axes


def midway(earlier: PseudoAttitude, later: PseudoAttitude) -> PseudoAttitude:
    """The pseudo-attitude half way between two (angles interpolated, yaw and roll wrapped;
    the covariance averaged)."""
    return PseudoAttitude(0.5 * (earlier.time_s + later.time_s),
                          wrap_pi(earlier.roll + 0.5 * wrap_pi(later.roll - earlier.roll)),
                          0.5 * (earlier.pitch + later.pitch),
                          wrap_pi(earlier.yaw + 0.5 * wrap_pi(later.yaw - earlier.yaw)),
                          0.5 * (earlier.covariance + later.covariance),
                          0.5 * (earlier.along_over_normal + later.along_over_normal))
