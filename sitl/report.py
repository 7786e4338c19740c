"""The flight report: the companion scored against simulator ground truth.

Inputs are the vehicle's flight log (sitl/flight_log.py: truth, and every VISION_*,
DISTANCE_SENSOR and setpoint message the autopilot received), the daemon's last telemetry
snapshot and every ``attitude_check`` payload it published (the attitude-only estimates). Nothing
here trusts the estimator's own opinion of itself: estimate errors are the received
VISION_POSITION_ESTIMATE positions, the attitude-only estimates and the DISTANCE_SENSOR heights
minus the truth at their capture time. A field that no pipeline provides yet is ``None`` (JSON
null), never invented.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from companion.frames import quat_from_euler, wrap_pi
from companion.mavlink.distance import ORIENTATION
from companion.scoring import WRONG_RESET_M, heading_nees, mean_or_none, nees, nees_band

SCHEMA = 1
ORIGIN_MATCH_M = 0.5
LOST_GAP_S = 0.3  # ArduPilot calls an external-nav source unhealthy after 300 ms
DEGRADED_SLOWDOWN = "estimate_degraded"  # the mission's failsafe kind for "slowed down", not a stop
# Issue 15's contract fields of the ``attitude`` block, each one statistic of one attitude source
# (the AttitudeEstimate ``source``): the GNSS + optic-flow pipeline's synthetic-flow path is
# "gnss_flow", its rendered-image (camera + LK) path "gnss_flow.images". Any other source is
# scored under ``attitude.sources`` only.
ATTITUDE_CONTRACT: dict[str, tuple[str, str]] = {
    "euler_mean_deg": ("gnss_flow", "euler_mean_deg"),
    "euler_std_deg": ("gnss_flow", "euler_std_deg"),
    "images_euler_std_deg": ("gnss_flow.images", "euler_std_deg"),
}
# The attitude sources' per-pair telemetry streams the harness keeps (only these keys of each
# payload): when a pair was flagged uncoordinated (no estimate), for ``uncoordinated_intervals_s``.
PAIR_STREAM_KEYS: dict[str, tuple[str, ...]] = {"gnss_flow": ("t_capture", "coordinated"),
                                                "gnss_flow_images": ("t_capture", "coordinated")}
INTERVAL_GAP_S = 1.0
LANDING_STEPS = ("land", "return_to_base")  # mission steps that end on the ground  # flagged samples this close in time form one interval
AGL_CEILING_M = 50.0  # heights above ground scored up to this true height (issue 15: "below 50 m")
AGL_FLOOR_M = 0.5  # ... and from this one: a percentage of a height near zero says nothing


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _interp_rows(t: np.ndarray, ts: np.ndarray, values: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(t, ts, values[:, k]) for k in range(values.shape[1])])


def capture_times(log: dict, usec: np.ndarray) -> np.ndarray:
    """Companion capture stamps (usec, daemon monotonic clock) -> simulation seconds."""
    t0 = log["clock"]["monotonic_at_sim_zero"]
    return usec * 1e-6 - (t0 or 0.0)


def _rate(times: list[float]) -> float | None:
    if len(times) < 2:
        return None
    span = times[-1] - times[0]
    return (len(times) - 1) / span if span > 0 else None


def score_estimate(log: dict) -> dict[str, float | None]:
    """Position/yaw/height error of the received vision estimates against truth."""
    vp = log["vision_position"]
    empty = dict.fromkeys(("position_rms_m", "position_max_m", "yaw_rms_deg", "attitude_rms_deg", "height_rms_m",
                           "fix_rate_hz", "lost_seconds", "nees_mean", "nees_band", "nees_max", "yaw_nees_mean",
                           "yaw_nees_band", "cross_track_max_m", "wrong_resets"))
    if not vp["usec"]:
        return empty
    truth = log["truth"]
    tt = np.asarray(truth["t"])
    tc = capture_times(log, np.asarray(vp["usec"], dtype=float))
    inside = (tc >= tt[0]) & (tc <= tt[-1])
    tc = tc[inside]
    est = np.asarray(vp["pos_ned"])[inside]
    true_pos = _interp_rows(tc, tt, np.asarray(truth["pos_ned"]))
    true_yaw = np.unwrap(np.asarray(truth["euler_rad"])[:, 2])
    est_euler = np.asarray(vp["euler_rad"])[inside]
    yaw_err = np.angle(np.exp(1j * (est_euler[:, 2] - np.interp(tc, tt, true_yaw))))
    horizontal = np.linalg.norm(est[:, :2] - true_pos[:, :2], axis=1)
    rx = np.asarray(vp["t_rx"])
    gaps = np.diff(np.concatenate([rx, [log["sim_seconds"]]]))
    triangles = [vp["position_covariance"][i] for i in np.flatnonzero(inside)]
    nees_values = position_nees(est - true_pos, triangles)
    band = nees_band(nees_values, 3)
    yaw_nees = heading_nees(yaw_err, [vp["yaw_variance"][i] for i in np.flatnonzero(inside)])
    yaw_band = nees_band(yaw_nees, 1)
    return {
        "position_rms_m": _rms(np.linalg.norm(est - true_pos, axis=1)),
        "position_max_m": float(np.max(np.linalg.norm(est - true_pos, axis=1))),
        "yaw_rms_deg": math.degrees(_rms(yaw_err)),
        "attitude_rms_deg": math.degrees(_rms(attitude_errors(est_euler, tc, tt, np.asarray(truth["euler_rad"])))),
        "height_rms_m": _rms(est[:, 2] - true_pos[:, 2]),
        "fix_rate_hz": None,  # measured fixes per second, from the daemon's pipeline statistics
        "lost_seconds": float(np.sum(gaps[gaps > LOST_GAP_S])),
        "nees_mean": mean_or_none(nees_values),
        "nees_band": None if band is None else list(band),
        "nees_max": float(nees_values.max()) if nees_values.size else None,
        "yaw_nees_mean": mean_or_none(yaw_nees),
        "yaw_nees_band": None if yaw_band is None else list(yaw_band),
        "cross_track_max_m": cross_track_max(est[:, :2] - true_pos[:, :2], triangles),
        "wrong_resets": wrong_resets(np.asarray(vp["reset_counter"])[inside], est, true_pos),
        "horizontal_rms_m": _rms(horizontal),
    }


def _euler_at(t: np.ndarray, truth_t: np.ndarray, truth_euler: np.ndarray) -> np.ndarray:
    """The true Euler angles (N, 3) rad at the times ``t`` (s), interpolated between the truth
    samples ``truth_euler`` (M, 3) at ``truth_t``; unwrapped, so a yaw through +/-180 deg
    interpolates the short way (not wrapped back into [-pi, pi))."""
    return _interp_rows(t, truth_t, np.column_stack([np.unwrap(truth_euler[:, k]) for k in range(3)]))


def attitude_errors(estimate_euler: np.ndarray, t: np.ndarray, truth_t: np.ndarray,
                    truth_euler: np.ndarray) -> np.ndarray:
    """Angle (rad) of the rotation between each estimated attitude (roll, pitch, yaw rad, (N, 3))
    and the true one at its capture time ``t`` (s): roll, pitch and yaw errors combined."""
    true = _euler_at(t, truth_t, truth_euler)
    est_q = np.array([quat_from_euler(*e) for e in estimate_euler]).reshape(-1, 4)
    true_q = np.array([quat_from_euler(*e) for e in true]).reshape(-1, 4)
    dot = np.abs(np.sum(est_q * true_q, axis=1))
    return 2.0 * np.arccos(np.clip(dot, 0.0, 1.0))


def euler_error_stats(estimate_euler: np.ndarray, t: np.ndarray, log: dict) -> dict[str, Any]:
    """Per-axis error of attitude estimates against the truth of the flight ``log``.

    ``estimate_euler`` (N, 3): roll, pitch, yaw rad (body FRD in NED, ZYX), NaN for an angle the
    estimate does not measure; ``t`` (N,): their capture times, simulation s. Each error is the
    estimate minus the truth at its capture time, wrapped to [-180, 180) deg; estimates outside
    the truth's time span are left out. Returns ``euler_mean_deg`` and ``euler_std_deg`` ([roll,
    pitch, yaw] deg: the mean and the sample standard deviation (ddof 1) of those errors, an
    axis None with too few measured values) and ``count`` (estimates scored)."""
    truth = log["truth"]
    tt = np.asarray(truth["t"], dtype=float)
    inside = (t >= tt[0]) & (t <= tt[-1]) if len(tt) else np.zeros(len(t), dtype=bool)
    if not inside.any():
        return {"euler_mean_deg": [None] * 3, "euler_std_deg": [None] * 3, "count": 0}
    errors = np.degrees(wrap_pi(estimate_euler[inside] - _euler_at(t[inside], tt, np.asarray(truth["euler_rad"]))))
    measured = [axis[np.isfinite(axis)] for axis in errors.T]
    return {"euler_mean_deg": [float(np.mean(a)) if len(a) else None for a in measured],
            "euler_std_deg": [float(np.std(a, ddof=1)) if len(a) > 1 else None for a in measured],
            "count": int(np.sum(inside))}


def flagged_intervals(log: dict, payloads: Sequence[dict], flagged: Callable[[dict], bool]) -> list[list[float]]:
    """[[start, end], ...] simulation seconds (capture times) of the ``payloads`` (each with a
    ``t_capture`` on the daemon clock) that are ``flagged``, samples within INTERVAL_GAP_S joined."""
    marked = [p["t_capture"] for p in payloads if flagged(p)]
    intervals: list[list[float]] = []
    for t in sorted(capture_times(log, np.array(marked, dtype=float) * 1e6).tolist()):
        if intervals and t - intervals[-1][1] <= INTERVAL_GAP_S:
            intervals[-1][1] = t
        else:
            intervals.append([t, t])
    return [[round(a, 2), round(b, 2)] for a, b in intervals]


def score_attitude(log: dict, attitude_checks: Sequence[dict],
                   pair_streams: Mapping[str, Sequence[dict]] | None = None) -> dict[str, Any]:
    """The attitude-only estimates (the daemon's ``attitude_check`` payloads, docs/telemetry.md)
    against the truth, per source: ``sources`` {source: :func:`euler_error_stats` plus
    ``alarm_intervals_s`` (while the cross-check against the autopilot's ATTITUDE was in alarm)
    and, from the source's per-pair stream in ``pair_streams`` (PAIR_STREAM_KEYS, the stream named
    as the source with '.' as '_'), ``uncoordinated_intervals_s`` (pairs flagged as uncoordinated
    flight: no estimate)}, and the contract's fields (ATTITUDE_CONTRACT) taken from those, None
    when their source made no estimate (one the autopilot's ATTITUDE was not known for yet is not
    published)."""
    by_source: dict[str, list[dict]] = {}
    for payload in attitude_checks:
        by_source.setdefault(payload["source"], []).append(payload)
    sources = {}
    for name, payloads in sorted(by_source.items()):
        euler = np.array([[math.nan if v is None else v for v in p["euler_rad"]] for p in payloads], dtype=float)
        t = capture_times(log, np.array([p["t_capture"] for p in payloads], dtype=float) * 1e6)
        sources[name] = euler_error_stats(euler, t, log)
        sources[name]["alarm_intervals_s"] = flagged_intervals(log, payloads, lambda p: bool(p.get("alarm")))
        pairs = (pair_streams or {}).get(name.replace(".", "_"))
        if pairs is not None:
            sources[name]["uncoordinated_intervals_s"] = flagged_intervals(
                log, pairs, lambda p: p.get("coordinated") is False)
    block: dict[str, Any] = {field: (sources.get(source) or {}).get(stat)
                             for field, (source, stat) in ATTITUDE_CONTRACT.items()}
    block["sources"] = sources
    return block


def distance_capture_times(log: dict) -> np.ndarray:
    """Simulation times (s) at which the received DISTANCE_SENSOR distances were measured: each
    message's ``time_boot_ms`` is the companion's capture time (ms on the daemon clock, modulo
    2^32), placed just before its reception by the signed difference between the two modulo 2^32."""
    ds = log["distance_sensor"]
    t_rx = np.asarray(ds["t_rx"], dtype=float)
    rx_daemon_ms = np.round((t_rx + (log["clock"]["monotonic_at_sim_zero"] or 0.0)) * 1e3).astype(np.int64)
    delay_ms = (rx_daemon_ms - np.asarray(ds["time_boot_ms"], dtype=np.int64) + 2**31) % 2**32 - 2**31
    return t_rx - delay_ms * 1e-3


def score_agl(log: dict, ground_height: Callable[[float, float], float]) -> tuple[float | None, int]:
    """Height above ground error of the downward DISTANCE_SENSOR distances the autopilot received.

    A downward distance is a rangefinder's, along the body z axis (ArduPilot multiplies it by the
    cosine of its tilt; the pipelines send height / cos(tilt)). Each is taken as the height it
    implies with the true tilt at its capture time (:func:`distance_capture_times`), distance *
    cos(roll) cos(pitch), and compared with the true height above the ground then: minus the true
    NED z, less ``ground_height(north, east)`` (m above the world's floor z = 0, e.g.
    World.floor_height_at) under the true position. Returns (the RMS over the samples of (implied
    - true height) / true height * 100, in %, or None without one; the number of samples), scoring
    the samples whose true height is within AGL_FLOOR_M to AGL_CEILING_M. Logs without
    DISTANCE_SENSOR records score None."""
    ds = log.get("distance_sensor")
    truth = log["truth"]
    if not ds or not ds["t_rx"] or not truth["t"]:
        return None, 0
    down = np.asarray(ds["orientation"]) == ORIENTATION["down"]
    t = distance_capture_times(log)[down]
    measured = np.asarray(ds["distance_m"], dtype=float)[down]
    tt = np.asarray(truth["t"], dtype=float)
    inside = (t >= tt[0]) & (t <= tt[-1])
    true_pos = _interp_rows(t[inside], tt, np.asarray(truth["pos_ned"], dtype=float)).reshape(-1, 3)
    true_height = -true_pos[:, 2] - np.array([ground_height(n, e) for n, e, _ in true_pos])
    scored = (true_height >= AGL_FLOOR_M) & (true_height <= AGL_CEILING_M)
    if not scored.any():
        return None, 0
    roll, pitch, _ = _euler_at(t[inside][scored], tt, np.asarray(truth["euler_rad"])).T
    implied = measured[inside][scored] * np.cos(roll) * np.cos(pitch)
    relative = (implied - true_height[scored]) / true_height[scored]
    return 100.0 * _rms(relative), int(np.sum(scored))


def position_nees(errors: np.ndarray, triangles: list[list[float | None]]) -> np.ndarray:
    """NEES (companion/scoring.py) of each 3-D position error with the covariance its estimate was
    sent with (rows [xx, xy, xz, yy, yz, zz], m^2): 3 is consistent. Estimates without a usable
    covariance are left out."""
    rows = [(e, tri) for e, tri in zip(errors, triangles) if tri is not None and not any(v is None for v in tri)]
    if not rows:
        return np.empty(0)
    tri = np.array([t for _, t in rows], dtype=float)
    cov = tri[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(-1, 3, 3)
    return nees(np.array([e for e, _ in rows]), cov)


def cross_track_max(errors: np.ndarray, triangles: list[list[float | None]]) -> float | None:
    """Largest horizontal error (m) along the direction each estimate's covariance is most certain
    of (its minor axis): in a corridor, the cross-track error, which the walls measure while the
    along-track one grows. None when no estimate carried a covariance."""
    worst = None
    for e, tri in zip(errors, triangles):
        if tri is None or any(v is None or not math.isfinite(v) for v in (tri[0], tri[1], tri[3])):
            continue  # no covariance sent (NaN: unknown, MAVLink's convention)
        _, vectors = np.linalg.eigh(np.array([[tri[0], tri[1]], [tri[1], tri[3]]], dtype=float))
        value = abs(float(e @ vectors[:, 0]))
        worst = value if worst is None else max(worst, value)
    return worst


def wrong_resets(reset_counter: np.ndarray, estimate: np.ndarray, truth: np.ndarray, limit_m: float = WRONG_RESET_M) -> int:
    """Position resets (``reset_counter`` changing) whose first estimate is more than ``limit_m``
    (horizontally) from the truth: a relocalization to the wrong place."""
    changed = np.flatnonzero(np.diff(reset_counter) != 0) + 1
    return int(np.sum(np.linalg.norm(estimate[changed, :2] - truth[changed, :2], axis=1) > limit_m))


def score_tracking(log: dict) -> tuple[float | None, float | None]:
    """RMS and max distance (m) of the truth from the position setpoints being commanded."""
    sp = log["setpoints"]
    masks = np.asarray(sp["type_mask"], dtype=int)
    if masks.size == 0:
        return None, None
    has_position = (masks & 0b111) == 0
    if not has_position.any():
        return None, None
    t = np.asarray(sp["t_rx"])[has_position]
    target = np.asarray(sp["pos"])[has_position]
    truth = log["truth"]
    true_pos = _interp_rows(t, np.asarray(truth["t"]), np.asarray(truth["pos_ned"]))
    err = np.linalg.norm(true_pos - target, axis=1)
    return _rms(err), float(err.max())


def _origin_matches(log: dict, origin: tuple[float, float, float]) -> bool:
    o = log["origin"]
    if o.get("set_at") is None:
        return False
    from companion.frames import ned_from_geodetic
    return float(np.linalg.norm(ned_from_geodetic(o["lat"], o["lon"], o["alt"], origin))) <= ORIGIN_MATCH_M


def _stage(system: dict, name: str, key: str) -> float | None:
    stage = (system.get("stage_ms") or {}).get(name)
    return None if stage is None else stage.get(key)


def score_recovery(log: dict, base_ne: tuple[float, float] | None) -> dict[str, Any] | None:
    """A return to base scored by truth (None for a world without a base): ``base_error_m`` the
    horizontal distance from the true landing point to the base (None unless landed and
    disarmed), ``final_distance_m`` the same at the end of the run whatever happened, and
    ``autopilot_position_lost_s``: how long the autopilot's own estimate had no position after
    it first had one (its EKF must keep one all the way home)."""
    if base_ne is None:
        return None
    truth = np.asarray(log["truth"]["pos_ned"], dtype=float)
    if len(truth) == 0:
        return {"base_error_m": None, "final_distance_m": None, "autopilot_position_lost_s": None}
    final = float(np.hypot(*(truth[-1, :2] - np.asarray(base_ne, dtype=float))))
    landed = bool(log["modes"]) and not log["modes"][-1][2]
    valid = np.asarray(log["vehicle_estimate"]["pos_valid"], dtype=bool)
    t = np.asarray(log["vehicle_estimate"]["t"], dtype=float)
    lost_s = None
    if valid.any():
        first = int(np.argmax(valid))
        dt = np.diff(t[first:], append=t[-1])
        lost_s = float(np.sum(dt[~valid[first:]]))
    return {"base_error_m": final if landed else None, "final_distance_m": final, "autopilot_position_lost_s": lost_s}


def build_report(*, mission: str, seconds: float, lockstep: bool, seed: int, control_law: str, log: dict,
                 telemetry: dict[str, dict], origin: tuple[float, float, float],
                 cpu_percent: float | None, rss_mb: float | None,
                 attitude_checks: Sequence[dict], ground_height: Callable[[float, float], float],
                 internal_errors: list[str] | None = None, base_ne: tuple[float, float] | None = None,
                 pair_streams: Mapping[str, Sequence[dict]] | None = None,
                 cpu_steal_percent: float | None = None) -> dict[str, Any]:
    """The report dict (schema 1) from a vehicle log and the daemon's last telemetry.

    ``attitude_checks``: every ``attitude_check`` payload the daemon published (and
    ``pair_streams``: every payload of the PAIR_STREAM_KEYS streams, those keys only), and
    ``ground_height`` (north, east m -> m above the floor z = 0): when there are attitude
    estimates or scored heights above ground, the report gains ``attitude``
    (:func:`score_attitude`, with ``agl_error_pct`` and ``agl_count`` from :func:`score_agl`).
    ``internal_errors``: what a real autopilot (ArduPilot SITL) stopped on during the run; None
    for the built-in vehicle, which has no such thing. ``base_ne``: the world's base (north,
    east m): the report gains ``recovery`` (:func:`score_recovery`). ``cpu_steal_percent``: the
    share of the machine's CPU time its hypervisor took during the run (None: not measured), which
    says whether a real-time run's timing figures came from an otherwise idle machine."""
    estimate = score_estimate(log)
    estimate.pop("horizontal_rms_m", None)
    system = telemetry.get("system", {})
    stats = telemetry.get("estimate_stats", {})
    if estimate["position_rms_m"] is not None:
        active = telemetry.get("sources", {}).get("active")  # the pose source the autopilot was fed by
        estimate["fix_rate_hz"] = (system.get("pipelines") or {}).get(active, {}).get("fix_rate_hz")
    tracking_rms, tracking_max = score_tracking(log)
    mission_state = telemetry.get("mission", {}).get("state")
    lands = telemetry.get("mission", {}).get("step_kind") in LANDING_STEPS  # its last step, once completed
    failsafes = telemetry.get("mission", {}).get("failsafe_counts") or {}
    landed_disarmed = bool(log["modes"]) and not log["modes"][-1][2]
    nonfinite = stats.get("nonfinite_dropped", 0) + stats.get("nonfinite_dropped_link", 0) if stats else None
    report: dict[str, Any] = {
        "schema": SCHEMA, "mission": mission, "seconds": seconds, "lockstep": lockstep, "seed": seed,
        "estimate": estimate,
        "autopilot": {
            "origin_confirmed": _origin_matches(log, origin) and bool(telemetry.get("autopilot", {}).get("origin_confirmed")),
            "external_nav_in_use": log["external_nav"]["first_in_use_at"] is not None,
            "vision_position_estimate_hz": _rate(log["vision_position"]["t_rx"]),
            "vision_speed_estimate_hz": _rate(log["vision_speed"]["t_rx"]),
            "setpoint_hz": _rate(log["setpoints"]["t_rx"]),
            "nonfinite_dropped": nonfinite,
            "firmware": telemetry.get("autopilot", {}).get("firmware"),
            "internal_errors": internal_errors,
        },
        "control": {
            "law": control_law,
            # every step done, and landed and disarmed if the mission ends with a landing (a fixed
            # wing's flight plan may end in the air, circling its last target)
            "mission_completed": mission_state == "completed" and (landed_disarmed or not lands),
            "tracking_rms_m": tracking_rms,
            "tracking_max_m": tracking_max,
            # stop / hold / land failsafes (estimate lost, geofence, pass tolerance), as the mission reported them
            "failsafes_triggered": sorted(kind for kind in failsafes if kind != DEGRADED_SLOWDOWN),
            "degraded_slowdowns": failsafes.get(DEGRADED_SLOWDOWN, 0),
        },
        "timing": {
            "lidar_ms_p50": _stage(system, "lidar", "p50"),
            "lidar_ms_p99": _stage(system, "lidar", "p99"),
            "fusion_ms_p50": _stage(system, "fusion", "p50"),
            "loop_jitter_ms_p99": (system.get("loop_jitter_ms") or {}).get("p99"),
            "cpu_percent": cpu_percent,
            "rss_mb": rss_mb,
            "cpu_steal_percent": cpu_steal_percent,
        },
    }
    agl_error_pct, agl_count = score_agl(log, ground_height)
    if attitude_checks or agl_count:
        report["attitude"] = {**score_attitude(log, attitude_checks, pair_streams), "agl_error_pct": agl_error_pct,
                              "agl_count": agl_count}
    recovery = score_recovery(log, base_ne)
    if recovery is not None:
        report["recovery"] = recovery
    return report
