"""Vehicle motion model and range / azimuth / elevation observation model of the EKF-SLAM.

Frames and units
----------------
World: MAVLink LOCAL_NED, metres: ``n`` north, ``e`` east, ``d`` down. The seed's ``x, y, psi``
are ``n, e, yaw`` (its ``tan^-1(y / x)`` is ``atan2(e, n)``), yaw clockwise from north, radians.
The vehicle's down coordinate ``d_v`` is not a state: the seed holds it constant (``z_v = 100 m``
up, ``d_v = -altitude``); the daemon's pipeline sets it to the measured height before each frame.
Vehicle state ``(n, e, yaw)``; landmark ``(n, e, d)``.

Observation of a landmark, with ``(dn, de, dd) = landmark - vehicle``, ``rho = hypot(dn, de)``
(horizontal distance), ``r = |(dn, de, dd)|``:

- range ``r`` (m);
- azimuth ``phi = atan2(de, dn) - yaw`` (rad, clockwise from the nose in the horizontal plane,
  wrapped to (-pi, pi]);
- elevation ``theta = atan2(-dd, rho)`` (rad, positive *above* the horizontal plane through
  the vehicle: a ground landmark below the vehicle has ``theta`` in (-pi/2, 0), about -70 to
  -90 degrees inside the seed's 20-degree nadir cone). This is the seed's eq. 4 / 24
  ``tan^-1((z_i - z_v) / rho)`` with its up axis (``z_up = -d``).

Motion model and its noise (seed eqs. 1-3, 16-21), the interpretation chosen
-----------------------------------------------------------------------------
Input ``u = (v, omega)``: ground speed along the heading (m/s) and yaw rate (rad/s), the
commanded / estimated velocity and heading change a UAV still has after GNSS loss (airspeed or
the autopilot's velocity estimate, the gyro's yaw rate). Over a step ``dt`` the heading change
is ``dpsi = omega * dt`` and::

    n_k   = n_{k-1} + v dt cos(yaw_{k-1} + dpsi)      (seed eq. 1 / 16)
    e_k   = e_{k-1} + v dt sin(yaw_{k-1} + dpsi)      (seed eq. 2 / 16)
    yaw_k = yaw_{k-1} + dpsi                          (seed eq. 3 / 16)

The seed's eqs. 1-3 *as printed* add the heading noise ``w_psi`` (Table 1: 2 deg) to the heading
at every 40 Hz step: a random walk of 2 deg * sqrt(40 * 100) = 126 deg after 100 s, which cannot
give its "about 36 m" INS-only error after a 500 m return, so the print is not what was
simulated. Table 1 is the default set of Tim Bailey's MATLAB ekfslam (DT_CONTROLS 0.025 s,
DT_OBSERVE 8 steps, MAXG 30 deg, RATEG 20 deg/s, sigmaV 0.2 m/s, sigmaG 2 deg), whose vehicle is
a bicycle of wheelbase WB = 4 m: ``yaw += v dt sin(G) / WB`` with the 2 deg noise on the
steering command ``G``. Mapped onto a UAV's inputs, that is white noise on the yaw *rate* of
``sigma_omega = v / WB * sigma_G`` (5 m/s / 4 m * 2 deg = 2.5 deg/s per 40 Hz sample, an angle
random walk of 2.5 * sqrt(0.025) = 0.40 deg/sqrt(s): a poor MEMS gyro), plus white noise of
0.2 m/s on the speed per sample. This module takes ``sigma_v`` and ``sigma_omega`` as given
(defaults in :class:`companion.nav.ekf_slam.config.EkfSlamConfig`); the filter's process noise
``Q = diag(sigma_v^2, sigma_omega^2)`` is exactly what the simulator draws, so the NEES means
something. Nothing is tuned to the seed's 36 m.

Jacobians (re-derived, seed eqs. 20-21, 28, 37-38)
--------------------------------------------------
Eq. 20 and 21 are right for ``u = (v, dpsi)``; with ``u = (v, omega)`` the ``dpsi`` column is
multiplied by ``dt``. Eq. 28 is right (with the seed's up axis). Eq. 30 prints ``W`` for the gain
``K``. Eq. 36 prints ``grad g_xv`` twice: its last block is ``grad g_z``. Eq. 38's entry
``d y_i / d theta`` is printed ``+r sin(phi + psi) sin(theta)``; differentiating eq. 33 gives
``-r sin(phi + psi) sin(theta)`` (the ``d x_i / d theta`` entry above it has the right sign).
In NED eq. 33's ``z_i = z_v + r sin(theta)`` is ``d_i = d_v - r sin(theta)``.
"""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * math.pi


def wrap(angle: float) -> float:
    """``angle`` (rad) wrapped to (-pi, pi]."""
    a = math.fmod(angle + math.pi, TWO_PI)
    if a <= 0.0:
        a += TWO_PI
    return a - math.pi


def motion(pose: np.ndarray, v_mps: float, omega_rps: float, dt_s: float, v_right_mps: float = 0.0) -> np.ndarray:
    """The vehicle pose ``(n, e, yaw)`` (m, m, rad) after ``dt_s`` at speed ``v_mps`` along the
    heading, ``v_right_mps`` across it (to the right; 0 in the seed, whose vehicle moves along its
    heading, but a multicopter crabs in wind) and yaw rate ``omega_rps`` (seed eqs. 1-3 without
    the noise, eq. 16)."""
    heading = pose[2] + omega_rps * dt_s
    c, s = math.cos(heading), math.sin(heading)
    return np.array([pose[0] + (v_mps * c - v_right_mps * s) * dt_s, pose[1] + (v_mps * s + v_right_mps * c) * dt_s,
                     wrap(heading)])


def motion_jacobians(pose: np.ndarray, v_mps: float, omega_rps: float, dt_s: float,
                     v_right_mps: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """``(F, G)``: derivatives of :func:`motion` by the pose (3 x 3, seed eq. 20) and by the
    input ``(v, v_right, omega)`` (3 x 3; seed eq. 21 with ``dpsi = omega dt`` and the lateral
    speed's column added)."""
    heading = pose[2] + omega_rps * dt_s
    c, s = math.cos(heading), math.sin(heading)
    dn, de = (v_mps * c - v_right_mps * s) * dt_s, (v_mps * s + v_right_mps * c) * dt_s
    f = np.array([[1.0, 0.0, -de], [0.0, 1.0, dn], [0.0, 0.0, 1.0]])
    g = np.array([[dt_s * c, -dt_s * s, -de * dt_s], [dt_s * s, dt_s * c, dn * dt_s], [0.0, 0.0, dt_s]])
    return f, g


def observe(pose: np.ndarray, down_m: float, landmark: np.ndarray) -> np.ndarray:
    """``(range m, azimuth rad, elevation rad)`` of ``landmark`` (n, e, d) seen from the vehicle
    at ``pose`` (n, e, yaw) and down coordinate ``down_m`` (seed eq. 4 / 24, NED; see the module
    docstring for the angles' conventions)."""
    dn, de, dd = landmark[0] - pose[0], landmark[1] - pose[1], landmark[2] - down_m
    rho = math.hypot(dn, de)
    return np.array([math.sqrt(rho * rho + dd * dd), wrap(math.atan2(de, dn) - pose[2]), math.atan2(-dd, rho)])


def observation_jacobian(delta: np.ndarray) -> np.ndarray:
    """3 x 3 derivative of ``(range, azimuth, elevation)`` by the landmark's ``(n, e, d)`` at the
    relative position ``delta = landmark - vehicle`` (n, e, d; m). By the vehicle's ``(n, e)``
    it is minus the first two columns; by the yaw it is ``(0, -1, 0)`` (seed eq. 28, re-derived
    in NED: the elevation row's last entry is ``-rho / r^2`` by ``d``, the seed's ``+rho / r^2``
    by its up coordinate)."""
    dn, de, dd = float(delta[0]), float(delta[1]), float(delta[2])
    rho2 = dn * dn + de * de
    rho = math.sqrt(rho2)
    r2 = rho2 + dd * dd
    r = math.sqrt(r2)
    k = dd / (r2 * rho)
    return np.array([
        [dn / r, de / r, dd / r],
        [-de / rho2, dn / rho2, 0.0],
        [dn * k, de * k, -rho / r2],
    ])


def full_observation_jacobian(delta: np.ndarray) -> np.ndarray:
    """3 x 6 derivative of the observation by ``(vehicle n, e, yaw, landmark n, e, d)``."""
    hl = observation_jacobian(delta)
    h = np.zeros((3, 6))
    h[:, 0:2] = -hl[:, 0:2]
    h[1, 2] = -1.0
    h[:, 3:6] = hl
    return h


def level_offset(z: np.ndarray) -> np.ndarray:
    """The landmark seen at ``z = (range, azimuth, elevation)`` as its offset ``(forward, right,
    down)`` (m) from the vehicle in the vehicle's heading frame (NED turned by the yaw only): the
    near-nadir form of an observation, where the azimuth is singular."""
    r, phi, theta = float(z[0]), float(z[1]), float(z[2])
    horizontal = r * math.cos(theta)
    return np.array([horizontal * math.cos(phi), horizontal * math.sin(phi), -r * math.sin(theta)])


def level_offset_cov(z: np.ndarray, sigmas: tuple[float, float, float]) -> np.ndarray:
    """3 x 3 covariance (m^2) of :func:`level_offset` for the observation noise ``sigmas`` (range
    m, azimuth rad, elevation rad) at ``z``. Range and elevation move the point radially (along the
    horizontal bearing) and down; across the bearing its sigma is the azimuth's ``rho sigma_az``
    but at least ``r sigma_el``: at the nadir the azimuth carries no information and a real
    sensor's angular noise is about alike in every direction (first-order propagation otherwise)."""
    r, phi, theta = float(z[0]), float(z[1]), float(z[2])
    s_r, s_az, s_el = sigmas
    ct, st = math.cos(theta), math.sin(theta)
    # (radial, down) by (range, elevation): radial = r cos(theta), down = -r sin(theta)
    j = np.array([[ct, -r * st], [-st, -r * ct]])
    radial_down = j @ np.diag([s_r * s_r, s_el * s_el]) @ j.T
    across = max(r * ct * s_az, r * s_el) ** 2
    cp, sp = math.cos(phi), math.sin(phi)
    basis = np.array([[cp, -sp, 0.0], [sp, cp, 0.0], [0.0, 0.0, 1.0]])  # (radial, across, down) -> (fwd, right, down)
    local = np.array([[radial_down[0, 0], 0.0, radial_down[0, 1]],
                      [0.0, across, 0.0],
                      [radial_down[1, 0], 0.0, radial_down[1, 1]]])
    return basis @ local @ basis.T


def predict_level_offset(pose: np.ndarray, down_m: float, landmark: np.ndarray) -> np.ndarray:
    """``(forward, right, down)`` (m) of ``landmark`` (n, e, d) from the vehicle at ``pose``
    (n, e, yaw) and ``down_m``: :func:`level_offset`'s prediction."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    dn, de = landmark[0] - pose[0], landmark[1] - pose[1]
    return np.array([c * dn + s * de, -s * dn + c * de, landmark[2] - down_m])


def level_offset_jacobian(yaw_rad: float, delta: np.ndarray) -> np.ndarray:
    """3 x 6 derivative of :func:`predict_level_offset` by ``(vehicle n, e, yaw, landmark n, e,
    d)`` at heading ``yaw_rad`` and relative position ``delta = landmark - vehicle`` (n, e, d; m):
    linear in the positions; by the yaw, ``(right, -forward, 0)``."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    forward = c * delta[0] + s * delta[1]
    right = -s * delta[0] + c * delta[1]
    h = np.zeros((3, 6))
    h[:, 0:2] = -rot[:, 0:2]
    h[:, 2] = [right, -forward, 0.0]
    h[:, 3:6] = rot
    return h


def inverse_observe(pose: np.ndarray, down_m: float, z: np.ndarray) -> np.ndarray:
    """The landmark ``(n, e, d)`` seen at ``z = (range, azimuth, elevation)`` from ``pose`` at
    ``down_m`` (seed eq. 33 in NED: ``d = d_v - r sin(theta)``)."""
    r, phi, theta = float(z[0]), float(z[1]), float(z[2])
    bearing = phi + pose[2]
    horizontal = r * math.cos(theta)
    return np.array([pose[0] + horizontal * math.cos(bearing), pose[1] + horizontal * math.sin(bearing),
                     down_m - r * math.sin(theta)])


def inverse_observe_jacobians(pose: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Gv, Gz)``: derivatives of :func:`inverse_observe` by the pose ``(n, e, yaw)`` (seed
    eq. 37) and by ``z`` (seed eq. 38 with the sign of ``d e / d theta`` corrected, NED)."""
    r, phi, theta = float(z[0]), float(z[1]), float(z[2])
    bearing = phi + pose[2]
    cb, sb, ct, st = math.cos(bearing), math.sin(bearing), math.cos(theta), math.sin(theta)
    gv = np.array([[1.0, 0.0, -r * sb * ct], [0.0, 1.0, r * cb * ct], [0.0, 0.0, 0.0]])
    gz = np.array([
        [cb * ct, -r * sb * ct, -r * cb * st],
        [sb * ct, r * cb * ct, -r * sb * st],
        [-st, 0.0, -r * ct],
    ])
    return gv, gz
