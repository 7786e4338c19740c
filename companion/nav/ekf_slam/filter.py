"""EKF-SLAM: a vehicle ``(n, e, yaw)`` at a known height (``down_m``: held, as in the seed, or
measured and set by the caller) and 3-D point landmarks with known ids.

State ``x = [n, e, yaw, (b_n, b_e,) l1_n, l1_e, l1_d, l2_n, ...]`` (LOCAL_NED metres, yaw clockwise
from north in radians; ``b``: the GNSS receiver's slowly wandering bias, first-order Gauss-Markov,
when ``gnss_bias_sigma_m`` > 0, so that the fixes anchor the map no more firmly than they can);
``P`` its covariance. Observations are ``(range m, azimuth rad, elevation rad)``
(:mod:`.model` for the conventions). Seed: Lee and Tahk 2010, eqs. 10-38; see :mod:`.model` for
the equations the seed prints wrongly.

Cost: :meth:`EkfSlam.predict` is O(n) (only the vehicle's rows and columns of ``P`` change);
:meth:`EkfSlam.update` is O(n^2) per landmark: the observation Jacobian has non-zero columns for
the vehicle's 3 and the landmark's 3 states only, so ``H P`` is computed from 6 rows of ``P`` and
the Joseph form ``(I - K H) P (I - K H)^T + K R K^T`` is evaluated as
``P - K (H P) - (H P)^T K^T + K S K^T`` (algebraically equal, with ``S = H P H^T + R``), itself as
``P + M + M^T`` with ``M = K (S K^T / 2 - H P)``: one n x 3 x n product and a correction that is
exactly symmetric, so ``P`` stays symmetric to the bit (prediction and augmentation keep it so).

Consistency: the textbook EKF-SLAM (``consistency="plain"``, the seed's) evaluates its Jacobians at
the latest estimates, which gives the filter spurious information about the global yaw (an
unobservable direction) and makes it over-confident as the heading uncertainty grows (Julier and
Uhlmann 2001; Bailey et al. 2006; Huang, Mourikis, Roumeliotis 2008/2010). ``"fej"`` applies the
first-estimates Jacobians of Huang et al.: the propagation Jacobian's yaw column uses the
difference between the new predicted position and the *previous predicted* position
``p_{k|k-1}`` (not the updated ``p_{k|k}``), and the observation Jacobian uses the predicted
vehicle position ``p_{k|k-1}`` and the landmark's *first* horizontal estimate (its down
coordinate from the latest estimate: with the altitude known it is observable, and it does not
enter the yaw null space). The innovation itself always uses the latest estimates.
"""

from __future__ import annotations

import math
import statistics
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from companion.nav.ekf_slam.config import EkfSlamConfig
from companion.nav.ekf_slam.model import (
    full_observation_jacobian,
    inverse_observe,
    inverse_observe_jacobians,
    level_offset,
    level_offset_cov,
    level_offset_jacobian,
    motion,
    motion_jacobians,
    observe,
    predict_level_offset,
    wrap,
)

VEHICLE = 3  # (n, e, yaw)
BIAS = slice(3, 5)  # the GNSS bias (n, e), m, when the filter has it: states 3 and 4
LANDMARK = 3  # (n, e, d)
POSITION_GATE_CHI2 = 13.82  # 99.9 % of chi-square with 2 degrees of freedom
LOST_MIN_M = 0.5  # a lost vehicle's inflated position sigma is at least this (m) ...
LOST_MAX_M = 50.0  # ... and is not inflated beyond this (m): a footprint and more


@dataclass
class UpdateResult:
    """What one :meth:`EkfSlam.update` did with each landmark id."""

    used: list[int] = field(default_factory=list)
    augmented: list[int] = field(default_factory=list)
    rejected: list[int] = field(default_factory=list)  # by the innovation gate
    skipped: list[int] = field(default_factory=list)  # new but too near the nadir, or taken as moved


class EkfSlam:
    """The EKF-SLAM of the seed (Sec. 3) with a Joseph-form O(n^2) update, gating, sub-maps and an
    optional first-estimates-Jacobians consistency fix. No I/O: the caller feeds inputs and
    observations and reads the estimates."""

    def __init__(self, config: EkfSlamConfig, pose: Iterable[float], pose_cov: np.ndarray) -> None:
        self.config = config
        self.down_m = config.down_m
        self.bias = config.gnss_bias_sigma_m > 0.0
        self.bias_var = config.gnss_bias_sigma_m ** 2
        self.head = VEHICLE + (2 if self.bias else 0)  # index of the first landmark state
        self.x = np.zeros(self.head)
        self.x[:VEHICLE] = list(pose)
        self.P = np.zeros((self.head, self.head))
        self.P[:VEHICLE, :VEHICLE] = np.asarray(pose_cov, dtype=float).reshape(VEHICLE, VEHICLE)
        if self.bias:
            self.P[BIAS, BIAS] = np.eye(2) * self.bias_var
        self.R = np.diag(config.r_matrix())
        sigma_v2, sigma_omega2 = config.q_matrix()
        self.Q = np.diag([sigma_v2, 0.0, sigma_omega2])  # inputs (v, v_right, omega): the seed's vehicle
        self.Q_lateral = np.diag([sigma_v2, sigma_v2, sigma_omega2])  # with a measured lateral speed
        self.fej = config.consistency == "fej"
        self.ids: list[int] = []  # landmark ids in state order
        self.slot: dict[int, int] = {}  # id -> offset of its first state in x
        self.first_ne: dict[int, np.ndarray] = {}  # id -> first horizontal estimate (FEJ)
        self.prior_ne = self.x[:2].copy()  # p_{k|k-1}: the vehicle position as last predicted
        self.rejections: Counter[int] = Counter()  # gate rejections per id, all time
        self._in_a_row: Counter[int] = Counter()
        self.moved: set[int] = set()  # ids rejected moved_after times in a row: no longer used
        self.lost_frames = 0  # frames in a row whose every known landmark the gate refused
        self.inflations = 0  # times the vehicle covariance was inflated for it
        self._work = np.empty((2, 0, 0))
        self.min_horizontal_m = config.min_horizontal_m
        self.sigmas = (config.sigma_range_m, math.radians(config.sigma_azimuth_deg),
                       math.radians(config.sigma_elevation_deg))

    # --- reading -----------------------------------------------------------------------------

    @property
    def n_landmarks(self) -> int:
        return len(self.ids)

    @property
    def pose(self) -> np.ndarray:
        """Vehicle ``(n, e, yaw)`` (m, m, rad), a copy."""
        return self.x[:VEHICLE].copy()

    @property
    def pose_cov(self) -> np.ndarray:
        """3 x 3 covariance of the vehicle pose, a copy."""
        return self.P[:VEHICLE, :VEHICLE].copy()

    def landmark(self, lid: int) -> tuple[np.ndarray, np.ndarray]:
        """``(mean (n, e, d), 3 x 3 covariance)`` of landmark ``lid`` (KeyError if not mapped)."""
        o = self.slot[lid]
        return self.x[o:o + 3].copy(), self.P[o:o + 3, o:o + 3].copy()

    def landmarks(self) -> dict[int, np.ndarray]:
        """Every mapped landmark's mean ``(n, e, d)`` by id (moved ones excepted)."""
        return {lid: self.x[o:o + 3].copy() for lid, o in self.slot.items() if lid not in self.moved}

    # --- prediction --------------------------------------------------------------------------

    def predict(self, v_mps: float, omega_rps: float, dt_s: float, v_right_mps: float | None = None,
                speed_sigma_mps: float | None = None) -> None:
        """Propagate the vehicle by the speed and yaw-rate inputs over ``dt_s`` (seed eqs. 16-21);
        ``v_right_mps``: a measured speed across the heading (a crabbing multicopter), noisy like
        the speed along it; None: the seed's vehicle, which moves along its heading (no lateral
        term, no lateral noise). ``speed_sigma_mps``: this step's speed noise (1-sigma, m/s, white
        per step) when the input states its own; None: the configured ``sigma_v_mps``.
        O(n): ``P_vv = F P_vv F^T + G Q G^T``, ``P_vm = F P_vm``."""
        pose = self.x[:VEHICLE]
        lateral = 0.0 if v_right_mps is None else v_right_mps
        f, g = motion_jacobians(pose, v_mps, omega_rps, dt_s, lateral)
        new = motion(pose, v_mps, omega_rps, dt_s, lateral)
        if self.fej:  # yaw column from p_{k+1|k} - p_{k|k-1} instead of p_{k+1|k} - p_{k|k}
            f[0, 2] = -(new[1] - self.prior_ne[1])
            f[1, 2] = new[0] - self.prior_ne[0]
        self.x[:VEHICLE] = new
        self.prior_ne = new[:2].copy()
        p = self.P
        q = self.Q_lateral if v_right_mps is not None else self.Q  # per input step (the seed's 40 Hz; the daemon's IMU rate)
        if speed_sigma_mps is not None:
            q = q.copy()
            q[0, 0] = speed_sigma_mps ** 2
            if v_right_mps is not None:
                q[1, 1] = speed_sigma_mps ** 2
        pvv = f @ p[:VEHICLE, :VEHICLE] @ f.T + g @ q @ g.T
        p[:VEHICLE, :VEHICLE] = 0.5 * (pvv + pvv.T)
        if p.shape[0] > VEHICLE:  # F = I except its yaw column: rows n and e gain f02 / f12 times row yaw
            cross = p[:VEHICLE, VEHICLE:]
            cross[0] += f[0, 2] * cross[2]
            cross[1] += f[1, 2] * cross[2]
            p[VEHICLE:, :VEHICLE] = cross.T
        if self.bias:  # first-order Gauss-Markov: b <- a b, variance kept at sigma^2 by the added noise
            a = math.exp(-dt_s / self.config.gnss_bias_tau_s)
            self.x[BIAS] *= a
            p[BIAS, :] *= a
            p[:, BIAS] *= a
            p[BIAS, BIAS] += np.eye(2) * self.bias_var * (1.0 - a * a)

    def move_vehicle(self, offset_ne: np.ndarray) -> None:
        """Shift the vehicle's estimated position (and its FEJ prediction point) by ``offset_ne``
        (north, east m), covariance unchanged: to use an observation captured a moment before the
        filter's time at the pose of that moment, and back."""
        self.x[:2] += offset_ne
        self.prior_ne = self.prior_ne + offset_ne

    # --- update ------------------------------------------------------------------------------

    def noise(self, sigmas: Sequence[float] | None) -> tuple[tuple[float, float, float], np.ndarray]:
        """``(sigmas, R)`` for a frame stating ``sigmas`` (range m, azimuth rad, elevation rad, the
        sensor's 1-sigma); the config's ``sigma_*`` when it states none, or none usable."""
        if sigmas is None or len(sigmas) != 3 or not all(math.isfinite(v) and v > 0.0 for v in sigmas):
            return self.sigmas, self.R
        values = (float(sigmas[0]), float(sigmas[1]), float(sigmas[2]))
        return values, np.diag(np.square(values))

    def update(self, observations: Mapping[int, np.ndarray],
               sigmas: Sequence[float] | Mapping[int, Sequence[float]] | None = None) -> UpdateResult:
        """Fuse one frame of observations ``{landmark id: (range, azimuth, elevation)}``: known
        landmarks update the state one after the other (seed eqs. 25-30, Joseph form, gated; the
        refused ones are tried once more after the accepted ones), new ids are added (seed eqs.
        31-38) after the known ones are used; a new id nearer the nadir than
        ``min_horizontal_m`` waits until it is seen further out. ``sigmas``: the noise the frame's
        sensor states (:meth:`noise`), one for all or by id."""
        def stated(lid: int) -> Sequence[float] | None:
            return sigmas.get(lid) if isinstance(sigmas, Mapping) else sigmas

        result = UpdateResult()
        new_ids = []
        for lid, z in observations.items():
            z = np.asarray(z, dtype=float)
            if lid in self.moved or (lid not in self.slot and self._near_nadir(z)):
                result.skipped.append(lid)
            elif lid not in self.slot:
                new_ids.append((lid, z))
            elif self._update_one(lid, z, stated(lid)):
                result.used.append(lid)
            else:
                result.rejected.append(lid)
        if result.used and result.rejected:  # once the accepted ones have moved the vehicle, again
            refused, result.rejected = result.rejected, []
            for lid in refused:
                (result.used if self._update_one(lid, np.asarray(observations[lid], dtype=float), stated(lid))
                 else result.rejected).append(lid)
        self._judge_rejections(result)
        for lid, z in new_ids:
            self.augment(lid, z, stated(lid))
            result.augmented.append(lid)
        return result

    def _judge_rejections(self, result: UpdateResult) -> None:
        """Who is wrong when the gate refuses observations. With at least two accepted and more
        accepted than refused, the vehicle agrees with the map and a refused landmark may have
        moved (taken as moved after ``moved_after`` such frames in a row). With some refused and
        no fewer accepted the vehicle is what is off: no landmark is blamed, and from the
        ``lost_after_frames``-th such frame in a row on its position covariance is inflated each
        frame (the standard deviation about doubled, at least ``LOST_MIN_M``, never beyond
        ``LOST_MAX_M``) until the map's landmarks pass the gate again and pull it back (the ids
        are known: no wrong association can follow). The heading is left alone: landmarks seen
        from above constrain it weakly, and a heading let loose turns the whole way home."""
        for lid in result.used:
            self._in_a_row[lid] = 0
        if len(result.used) >= 2 and len(result.used) > len(result.rejected):
            self.lost_frames = 0
            for lid in result.rejected:
                self._in_a_row[lid] += 1
                if self._in_a_row[lid] >= self.config.moved_after:
                    self.moved.add(lid)
        elif result.rejected and len(result.rejected) >= len(result.used):
            self.lost_frames += 1
            position_sigma = math.sqrt(max(self.P[0, 0] + self.P[1, 1], 0.0))
            if self.lost_frames >= self.config.lost_after_frames and position_sigma < LOST_MAX_M:
                self.inflations += 1
                grow = 1.5 * max(position_sigma, LOST_MIN_M) ** 2  # per axis: about twice the sigma
                self.P[0, 0] += grow
                self.P[1, 1] += grow
        else:
            self.lost_frames = 0

    def _near_nadir(self, z: np.ndarray) -> bool:
        """Is the landmark seen at ``z`` horizontally nearer than ``min_horizontal_m``?"""
        return z[0] * math.cos(z[2]) < self.min_horizontal_m

    def innovation(self, lid: int, z: np.ndarray, sigmas: Sequence[float] | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
        """``(nu, H (3 x 6), S, state indices)`` of observation ``z`` of mapped landmark ``lid``.
        Near the nadir (``min_horizontal_m``), where the azimuth is singular and its linearisation
        wrong by more than its noise, the observation is used as its offset in the heading frame
        (:func:`.model.level_offset`, linear in the positions) with its propagated covariance:
        a vehicle descending onto a landmark keeps it in use all the way down."""
        o = self.slot[lid]
        idx = [0, 1, 2, o, o + 1, o + 2]
        landmark = self.x[o:o + 3]
        pose = self.x[:VEHICLE]
        if self.fej:
            first = self.first_ne[lid]
            delta = np.array([first[0] - self.prior_ne[0], first[1] - self.prior_ne[1], landmark[2] - self.down_m])
        else:
            delta = np.array([landmark[0] - pose[0], landmark[1] - pose[1], landmark[2] - self.down_m])
        if self._near_nadir(z):
            nu = level_offset(z) - predict_level_offset(pose, self.down_m, landmark)
            h = level_offset_jacobian(float(pose[2]), delta)
            r = level_offset_cov(z, self.noise(sigmas)[0])
        else:
            nu = np.asarray(z, dtype=float) - observe(pose, self.down_m, landmark)
            nu[1] = wrap(nu[1])
            h = full_observation_jacobian(delta)
            r = self.noise(sigmas)[1]
        s = h @ self.P[np.ix_(idx, idx)] @ h.T + r
        return nu, h, s, idx

    def _update_one(self, lid: int, z: np.ndarray, sigmas: Sequence[float] | None) -> bool:
        nu, h, s, idx = self.innovation(lid, z, sigmas)
        s_inv = _inverse(s)
        if s_inv is None or float(nu @ s_inv @ nu) > self.config.gate_chi2:
            self.rejections[lid] += 1
            return False
        self._correct(h @ self.P[idx, :], s, s_inv, nu)  # H P from 6 rows of P
        return True

    def _correct(self, hp: np.ndarray, s: np.ndarray, s_inv: np.ndarray, nu: np.ndarray) -> None:
        """The Kalman correction for an m-row measurement given ``H P`` (m x n), its innovation
        covariance ``S`` (m x m, and its inverse) and innovation ``nu`` (m,)."""
        p = self.P
        k = hp.T @ s_inv  # n x m
        self.x += k @ nu
        self.x[2] = wrap(self.x[2])
        # Joseph form (I-KH)P(I-KH)^T + KRK^T = P - K(HP) - (HP)^T K^T + K S K^T = P + M + M^T
        # with M = K (S K^T / 2 - HP): one n x m x n product, and M + M^T is exactly symmetric
        n = p.shape[0]
        if self._work.shape[1] != n:  # kept n x n buffers: fresh ones each update cost page faults
            self._work = np.empty((2, n, n))
        m = np.matmul(k, 0.5 * (s @ k.T) - hp, out=self._work[0])
        p += np.add(m, m.T, out=self._work[1])

    def update_position(self, ne: np.ndarray, cov: np.ndarray) -> bool:
        """Fuse a measurement of the vehicle's horizontal position (a GNSS fix: ``ne`` (2,) m NED,
        ``cov`` 2 x 2 m^2, the receiver's whole stated error): linear, so no Jacobian question;
        gated at the 99.9 % chi-square of 2 degrees of freedom (13.8). False (nothing changed)
        when gated out.

        With bias states (``gnss_bias_sigma_m`` > 0) the fix measures position plus bias, and only
        the rest of its variance (at least a tenth of it) is white; without, the fix is white
        noise (the seed's simulations have no GNSS)."""
        cov = np.asarray(cov, dtype=float)
        nu = np.asarray(ne, dtype=float) - self.x[:2]
        hp = self.P[:2, :].copy()
        if self.bias:
            nu -= self.x[BIAS]
            hp += self.P[BIAS, :]
            cov = np.maximum(cov - np.eye(2) * self.bias_var, 0.1 * cov)
        s = hp[:, :2] + cov
        if self.bias:
            s += hp[:, BIAS]
        s_inv = _inverse(s)
        if s_inv is None or float(nu @ s_inv @ nu) > POSITION_GATE_CHI2:
            return False
        self._correct(hp, s, s_inv, nu)
        return True

    def augment(self, lid: int, z: np.ndarray, sigmas: Sequence[float] | None = None) -> None:
        """Add landmark ``lid`` first seen at ``z`` (seed eqs. 31-38):
        ``l = g(x_v, z)``, ``P_ll = Gv P_vv Gv^T + Gz R Gz^T``, ``P_lx = Gv P_vx`` (``R`` from the
        frame's ``sigmas``, :meth:`noise`)."""
        if lid in self.slot:
            raise ValueError(f"landmark {lid} is already mapped")
        z = np.asarray(z, dtype=float)
        pose = self.x[:VEHICLE]
        landmark = inverse_observe(pose, self.down_m, z)
        gv, gz = inverse_observe_jacobians(pose, z)
        n = self.x.shape[0]
        p_lx = gv @ self.P[:VEHICLE, :]  # 3 x n
        p_ll = gv @ self.P[:VEHICLE, :VEHICLE] @ gv.T + gz @ self.noise(sigmas)[1] @ gz.T
        big = np.empty((n + LANDMARK, n + LANDMARK))
        big[:n, :n] = self.P
        big[n:, :n] = p_lx
        big[:n, n:] = p_lx.T
        big[n:, n:] = 0.5 * (p_ll + p_ll.T)
        self.P = big
        self.x = np.concatenate([self.x, landmark])
        self.slot[lid] = n
        self.ids.append(lid)
        self.first_ne[lid] = landmark[:2].copy()

    # --- sub-maps ----------------------------------------------------------------------------

    def start_submap(self, keep_landmark: int | None = None, keep_cross: bool = True,
                     also_keep: Iterable[int] = ()) -> None:
        """Start a new sub-map (seed Sec. 4 STEP 6): keep the vehicle pose and its covariance and,
        if ``keep_landmark`` is given, that landmark (the new start point) with its covariance and,
        if ``keep_cross``, its cross-covariances with the vehicle (and the other kept landmarks);
        drop every other landmark (marginalising them out: the kept block of ``P`` is unchanged).
        ``also_keep``: further mapped ids to keep (e.g. those in view at the new start point; not
        the seed's, which keeps none). Gate counters of dropped landmarks are kept (an id seen
        again is a new landmark of the new sub-map)."""
        keep = list(range(self.head))
        kept_ids = []
        for lid in ([keep_landmark] if keep_landmark is not None else []) + list(also_keep):
            if lid in self.slot and lid not in kept_ids:
                o = self.slot[lid]
                keep += [o, o + 1, o + 2]
                kept_ids.append(lid)
        self.x = self.x[keep].copy()
        self.P = self.P[np.ix_(keep, keep)].copy()
        if kept_ids and not keep_cross:
            self.P[:self.head, self.head:] = 0.0
            self.P[self.head:, :self.head] = 0.0
        self.ids = kept_ids
        self.slot = {lid: self.head + 3 * i for i, lid in enumerate(kept_ids)}
        self.first_ne = {lid: self.first_ne[lid] for lid in kept_ids}


def _inverse(s: np.ndarray) -> np.ndarray | None:
    """The inverse of an innovation covariance, None if it is singular or not finite (the
    measurement is then refused, never raised into the caller's cycle)."""
    if not np.all(np.isfinite(s)):
        return None
    try:
        return np.linalg.inv(s)
    except np.linalg.LinAlgError:
        return None


def nees(error: np.ndarray, cov: np.ndarray) -> float:
    """Normalised estimation error squared ``e^T P^-1 e`` (for a pose error give the yaw wrapped)."""
    e = np.asarray(error, dtype=float)
    return float(e @ np.linalg.solve(cov, e))


def pose_error(truth: np.ndarray, estimate: np.ndarray) -> np.ndarray:
    """``estimate - truth`` for ``(n, e, yaw)`` with the yaw difference wrapped (m, m, rad)."""
    e = np.asarray(estimate, dtype=float)[:3] - np.asarray(truth, dtype=float)[:3]
    e[2] = wrap(e[2])
    return e


def chi2_quantile(p: float, dof: float) -> float:
    """Chi-square quantile by the Wilson-Hilferty approximation (relative error below 1 % for
    ``dof >= 3`` at the 2.5 / 97.5 % points; numpy has no chi-square quantile, scipy is not a
    dependency)."""
    z = statistics.NormalDist().inv_cdf(p)
    k = 2.0 / (9.0 * dof)
    return dof * (1.0 - k + z * math.sqrt(k)) ** 3


def nees_band(dof: int, runs: int, probability: float = 0.95) -> tuple[float, float]:
    """The two-sided ``probability`` band of the average NEES over ``runs`` Monte-Carlo runs of a
    consistent filter with ``dof``-dimensional errors: ``chi2(dof * runs) / runs``."""
    tail = (1.0 - probability) / 2.0
    n = dof * runs
    return chi2_quantile(tail, n) / runs, chi2_quantile(1.0 - tail, n) / runs
