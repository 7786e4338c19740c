"""Scores of an estimate against a reference (simulator truth or a log's own poses), shared by the
SITL flight report (sitl/report.py) and `companion replay` (companion/replay.py).

Nothing here looks at the estimator's opinion of itself except through its covariance, which is
what NEES checks.
"""

from __future__ import annotations

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


def mean_or_none(values: np.ndarray) -> float | None:
    """The mean of ``values``, None when there are none."""
    return float(np.mean(values)) if len(values) else None
