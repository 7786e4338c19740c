"""Pose hypotheses from corners (relocalization by corners; companion/nav/planar.py).

Observed corners (levelled body frame, metres) against map corners (map frame, LOCAL_NED north,
east, metres) at a few candidate headings (rad, from north towards east): every pairing proposes
the translation that puts the observed corner on the map one; a translation many observed
corners agree on (within a tolerance) is a hypothesis. The planar localizer refines the best
distinct ones and keeps a clear winner.
"""

from __future__ import annotations

import math

import numpy as np

from companion.frames import planar_rotation
from companion.nav.corner_shape import shapes_agree


def pose_hypotheses(observed: np.ndarray, landmarks: np.ndarray, yaws: np.ndarray, tolerance: float,
                     min_score: int, shapes: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Rows (score, yaw, x, y): every (heading, observed corner i -> map corner a) hypothesis
    scoring at least ``min_score``, best first. The score counts the observed corners j that
    have a map corner b with (b - R q_j) within ``tolerance`` of the hypothesis translation.

    Each (j, b) pair proposes the translation ``b - R q_j``; the score is the number of distinct
    observed corners among the proposals within ``tolerance`` of the hypothesis' own. Proposals
    are bucketed in a grid of ``2 tolerance`` cells, so only neighbouring cells are compared, and
    only for proposals with ``min_score`` of them nearby: time and memory grow with k * m
    (observed times map corners), not (k * m)^2.

    ``shapes`` (rays (k, 2, 2) of the observed corners in their own frame, the cosines of their
    largest angles (k, 2), the map corners' rays (m, R, 2): corner_shape.py): a pair proposes
    nothing unless the corners' walls run the same ways at that heading, as the localizer's
    association requires, so a corner cannot vote for a pose that puts it on a corner of another
    shape (the back of a door recess on its mouth)."""
    k, m = observed.shape[0], landmarks.shape[0]
    owner = np.repeat(np.arange(k), m)  # the observed corner of each proposal, row i * m + a
    if shapes is not None:  # a map has few distinct shapes (a building's corners repeat them): compare those
        rays, limits, map_rays = shapes
        kinds, kind = np.unique(map_rays.reshape(m, 2 * map_rays.shape[1]), axis=0, return_inverse=True)
        kinds, kind = kinds.reshape(-1, *map_rays.shape[1:]), kind.reshape(-1)
    rows = []
    for yaw in yaws:
        rotation = planar_rotation(float(yaw))
        trans = (landmarks[None, :, :] - (observed @ rotation.T)[:, None, :]).reshape(-1, 2)
        owners = owner
        if shapes is not None:
            alike = shapes_agree((rays @ rotation.T)[:, None], limits[:, None], kinds[None])[:, kind]
            trans, owners = trans[alike.ravel()], owner[alike.ravel()]
        score = _owners_within(trans, owners, k, tolerance, min_score)
        good = score >= min_score
        rows.append(np.column_stack((score[good], np.full(good.sum(), yaw), trans[good])))
    out = np.concatenate(rows) if rows else np.zeros((0, 4))
    return out[np.argsort(-out[:, 0], kind="stable")]


def _owners_within(points: np.ndarray, owner: np.ndarray, owners: int, radius: float,
                   at_least: int) -> np.ndarray:
    """For every point of ``points`` (n, 2), how many distinct ``owner`` values (0 .. owners-1) the
    points within ``radius`` of it (itself included) have; 0 for the points that cannot reach
    ``at_least`` (fewer points than that near them: the count is not needed there).

    Grid of ``2 radius`` cells: the points within ``radius`` of a point lie in the 2 x 2 block of
    cells around the cell corner nearest to it, so four lookups per point; the pairs are compared
    only for points whose block holds ``at_least`` points (most proposals of a large map have no
    neighbour at all)."""
    n = points.shape[0]
    counts = np.zeros(n, dtype=int)
    if n == 0:
        return counts
    scaled = points / (2.0 * radius)
    cell = np.floor(scaled).astype(np.int64)
    step = np.where(scaled - cell >= 0.5, 1, -1)  # towards the nearer neighbour, per axis
    cell -= cell.min(axis=0) - 1  # >= 1, so that a neighbour's index stays >= 0
    width = int(cell[:, 1].max()) + 2
    key = cell[:, 0] * width + cell[:, 1]
    # Work in cell order: the lookups below then search nearly sorted keys (numpy's binary search
    # starts from its previous answer), and a point's own cell is its run.
    order = np.argsort(key, kind="stable")
    key, step, xy, own = key[order], step[order], points[order], owner[order]
    run_start = np.concatenate(([True], key[1:] != key[:-1]))
    first = np.flatnonzero(run_start)
    keys, count = key[first], np.diff(np.append(first, n))
    slots = [np.cumsum(run_start) - 1]
    hits = [count[slots[0]]]
    for dx, dy in ((1, 0), (0, 1), (1, 1)):
        wanted = key + (dx * step[:, 0] * width + dy * step[:, 1])
        slot = np.minimum(np.searchsorted(keys, wanted), keys.size - 1)
        slots.append(slot)
        hits.append(np.where(keys[slot] == wanted, count[slot], 0))
    candidates = np.flatnonzero(sum(hits) >= at_least)
    if candidates.size == 0:
        return counts
    seen = np.zeros((candidates.size, owners), dtype=bool)  # candidate x owner: a neighbour of that owner
    for slot, hit in zip(slots, hits):
        slot, hit = slot[candidates], hit[candidates]
        total = int(hit.sum())
        if total == 0:
            continue
        row = np.repeat(np.arange(candidates.size), hit)
        b = np.repeat(first[slot], hit) + np.arange(total) - np.repeat(np.cumsum(hit) - hit, hit)
        d = xy[candidates[row]] - xy[b]
        near = d[:, 0] ** 2 + d[:, 1] ** 2 <= radius ** 2
        seen[row[near], own[b[near]]] = True
    counts[order[candidates]] = seen.sum(axis=1)
    return counts


def distinct_poses(poses: np.ndarray, distinct_m: float, limit: int) -> list[np.ndarray]:
    """The first ``limit`` best-first pose rows that are not near a kept one of the same yaw."""
    kept: list[np.ndarray] = []
    for row in poses:
        if not any(row[1] == k[1] and math.hypot(row[2] - k[2], row[3] - k[3]) < distinct_m for k in kept):
            kept.append(row)
            if len(kept) == limit:
                break
    return kept
