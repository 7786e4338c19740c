"""Scores of an estimate against a reference (simulator truth or a log's own poses), shared by the
SITL flight report (sitl/report.py) and `companion replay` (companion/replay.py).

Nothing here looks at the estimator's opinion of itself except through its covariance, which is
what NEES checks.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

WRONG_RESET_M = 0.5  # a relocalization (reset) landing farther than this from the reference is a wrong one


def nees(errors: np.ndarray, covariances: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared per estimate: e^T P^-1 e for ``errors`` (N, k) and
    ``covariances`` (N, k, k) in the same units (e.g. m and m^2). Its mean is k for a consistent
    estimator (95 % band over N independent estimates: k +/- 1.96 sqrt(2 k / N)); below, over-
    cautious; above, over-confident. Estimates whose covariance cannot be inverted are left out."""
    errors = np.asarray(errors, dtype=float)
    covariances = np.asarray(covariances, dtype=float)
    if errors.shape[0] == 0:
        return np.empty(0)
    good = np.linalg.cond(covariances) < 1e12
    solved = np.linalg.solve(covariances[good], errors[good][..., None])[..., 0]
    return np.einsum("ij,ij->i", errors[good], solved)


def heading_nees(errors_rad: np.ndarray, variances_rad2: Sequence[float | None] | np.ndarray) -> np.ndarray:
    """NEES of each heading error (rad, wrapped to [-pi, pi)) with the variance (rad^2) its estimate
    claimed: 1 is consistent. Estimates without a positive variance (None, zero) are left out."""
    variances = np.array([np.nan if v is None else v for v in variances_rad2], dtype=float)
    errors = np.asarray(errors_rad, dtype=float)
    good = np.isfinite(variances) & (variances > 0.0) & np.isfinite(errors)
    return errors[good] ** 2 / variances[good]


def effective_samples(values: np.ndarray) -> float:
    """How many independent samples a correlated series is worth: N / (1 + 2 sum of its
    autocorrelations), summed up to the first lag where they stop being positive (Geyer's
    initial positive sequence). Estimates at 30 Hz are far from independent."""
    x = np.asarray(values, dtype=float)
    n = x.size
    if n < 3:
        return float(n)
    x = x - x.mean()
    var = float(x @ x) / n
    if var <= 0.0:
        return float(n)
    spectrum = np.fft.rfft(x, 2 * n)
    acf = np.fft.irfft(spectrum * np.conj(spectrum))[:n] / (n * var)
    stop = np.flatnonzero(acf[1:] <= 0.0)
    tail = acf[1:1 + (stop[0] if stop.size else n - 1)]
    return float(n / (1.0 + 2.0 * tail.sum()))


def nees_band(values: np.ndarray, dof: int) -> tuple[float, float] | None:
    """The 95 % band of a consistent estimator's mean NEES (``dof`` dimensions) over ``values``,
    counting them as the independent samples they are worth (:func:`effective_samples`):
    dof +/- 1.96 sqrt(2 dof / N_eff). None without values."""
    if len(values) == 0:
        return None
    half = 1.96 * float(np.sqrt(2.0 * dof / max(effective_samples(values), 1.0)))
    return (dof - half, dof + half)


def mean_or_none(values: np.ndarray) -> float | None:
    """The mean of ``values``, None when there are none."""
    return float(np.mean(values)) if len(values) else None
