"""`companion experiment slam-recovery --seeds 30 --out R.json`: the three simulations of Lee and
Tahk 2010 (Sec. 5) as a seeded Monte-Carlo, scored against the simulator's truth.

World: point landmarks scattered uniformly over [-150, 650] m x [-150, 650] m (north, east),
:data:`DENSITY_PER_KM2` per square kilometre (one per 1000 m^2: a 36 m footprint holds about four),
heights 0-5 m above the ground datum (NED down 0 to -5 m). The jam point is the origin, the base
(353.5, 353.5) m, 500 m away. Each seed draws its own landmarks and noise.

Vehicle: 100 m altitude (NED down -100), 5 m/s. Steering as in Tim Bailey's ekfslam simulator,
whose defaults are the seed's Table 1: a heading command ``G`` (limited to 30 deg and 20 deg/s)
towards the point the vehicle steers at, yaw rate ``v sin(G) / 4 m`` -- the steering uses the
*estimate*, as a real vehicle must. The true vehicle follows its commanded speed and yaw rate
exactly; the filter receives them with white noise (0.2 m/s, 2.5 deg/s per 40 Hz step: the
interpretation of Table 1 documented in companion/nav/ekf_slam/model.py), the same noise its
``Q`` assumes. Sensor: 5 Hz, nadir cone of 20 deg half angle, range / azimuth / elevation with
0.2 m / 0.16 deg / 0.12 deg noise, known ids. The last good fix is exact (the seed's assumption):
the initial covariance is a centimetre and a hundredth of a degree, the initial error drawn from it.

1. five loops on a circle (radius 0.8 footprint) around the landmark nearest the origin:
   vehicle position RMS over each loop and map RMS at each loop's end;
2. dead reckoning only, straight from the origin to the base: error where the estimate reaches
   the base;
3. the recovery planner (companion/nav/ekf_slam/planner.py) with sub-maps: error between truth
   and estimate where the planner lands (it believes it is within 1 m of the base); the vehicle
   pose NEES against the 95 % band of the average over the runs. Run with the first-estimates
   Jacobians (``fej``) and with the plain EKF-SLAM (the baseline) on the same seeds. A new
   sub-map keeps the landmarks in view at its start point (``--submap-keep in_view``, default)
   or only the start landmark as the seed does (``--submap-keep start``).

Figures are medians over the seeds (simulation 3: over the runs that landed; the landed fraction
is reported beside). Seed paper: INS only about 36 m at the base, the proposed
method below 2 m (its Figs. 12-13).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from companion.nav.ekf_slam.config import EkfSlamConfig, RecoveryPlannerConfig
from companion.nav.ekf_slam.filter import EkfSlam, nees, nees_band, pose_error
from companion.nav.ekf_slam.model import motion, observe, wrap
from companion.nav.ekf_slam.planner import RecoveryPlanner

BASE_NE = (353.5, 353.5)
AREA_NE = ((-150.0, 650.0), (-150.0, 650.0))
DENSITY_PER_KM2 = 1000.0
MAX_HEIGHT_M = 5.0
SPEED_MPS = 5.0
DT_S = 0.025  # 40 Hz motion input (Table 1)
OBSERVE_EVERY = 8  # 5 Hz sensor (Table 1)
MAX_G_RAD = math.radians(30.0)  # heading command limit (Table 1)
RATE_G_RPS = math.radians(20.0)  # heading command rate limit (Table 1)
WHEELBASE_M = 4.0  # Bailey's: yaw rate = v sin(G) / WB
INITIAL_SIGMA = (0.01, 0.01, math.radians(0.01))  # last good fix: n, e (m), yaw (rad)
SIM1_LOOPS = 5
MAX_TIME_S = 3000.0
SEED_PAPER = {"sim2_base_error_m": 36.0, "sim3_base_error_m": "below 2"}


@dataclass
class World:
    landmarks: np.ndarray  # (k, 3) n, e, d (m)


def make_world(rng: np.random.Generator) -> World:
    (n0, n1), (e0, e1) = AREA_NE
    count = int(round(DENSITY_PER_KM2 * (n1 - n0) * (e1 - e0) / 1e6))
    pts = np.column_stack([rng.uniform(n0, n1, count), rng.uniform(e0, e1, count),
                           -rng.uniform(0.0, MAX_HEIGHT_M, count)])
    return World(pts)


@dataclass
class Vehicle:
    """Truth, the steering state, and the noise sources of one run."""

    pose: np.ndarray
    rng: np.random.Generator
    cfg: EkfSlamConfig
    g: float = 0.0
    distance_m: float = 0.0

    def steer(self, estimate: np.ndarray, carrot: tuple[float, float]) -> float:
        """Yaw rate (rad/s) commanded towards ``carrot`` from the *estimated* pose (Bailey's
        compute_steering with the Table 1 limits)."""
        desired = math.atan2(carrot[1] - estimate[1], carrot[0] - estimate[0])
        dg = wrap(desired - estimate[2] - self.g)
        dg = max(-RATE_G_RPS * DT_S, min(RATE_G_RPS * DT_S, dg))
        self.g = max(-MAX_G_RAD, min(MAX_G_RAD, self.g + dg))
        return SPEED_MPS * math.sin(self.g) / WHEELBASE_M

    def move(self, omega: float) -> tuple[float, float]:
        """Advance the truth one step; the noisy (speed, yaw rate) the navigation receives."""
        self.pose = motion(self.pose, SPEED_MPS, omega, DT_S)
        self.distance_m += SPEED_MPS * DT_S
        return (SPEED_MPS + self.rng.normal(0.0, self.cfg.sigma_v_mps),
                omega + self.rng.normal(0.0, math.radians(self.cfg.sigma_omega_dps)))


def sense(world: World, pose: np.ndarray, cfg: EkfSlamConfig, rng: np.random.Generator) -> dict[int, np.ndarray]:
    """Noisy observations ``{id: (range, azimuth, elevation)}`` of the landmarks in the nadir cone."""
    lm = world.landmarks
    dn, de = lm[:, 0] - pose[0], lm[:, 1] - pose[1]
    below = lm[:, 2] - cfg.down_m  # > 0: landmark below the vehicle
    tan_fov = math.tan(math.radians(cfg.half_fov_deg))
    seen = np.flatnonzero(dn * dn + de * de <= (below * tan_fov) ** 2)
    sig = np.array([cfg.sigma_range_m, math.radians(cfg.sigma_azimuth_deg), math.radians(cfg.sigma_elevation_deg)])
    out = {}
    for i in seen:
        z = observe(pose, cfg.down_m, lm[i]) + rng.normal(0.0, 1.0, 3) * sig
        z[1] = wrap(z[1])
        out[int(i)] = z
    return out


def _start(rng: np.random.Generator, cfg: EkfSlamConfig, truth: np.ndarray) -> tuple[Vehicle, EkfSlam]:
    p0 = np.diag(np.square(INITIAL_SIGMA))
    est = truth + rng.normal(0.0, 1.0, 3) * np.array(INITIAL_SIGMA)
    return Vehicle(truth.copy(), rng, cfg), EkfSlam(cfg, est, p0)


def _horizontal_error(vehicle: Vehicle, slam: EkfSlam) -> float:
    return float(np.hypot(*(vehicle.pose[:2] - slam.x[:2])))


def _map_rms(world: World, slam: EkfSlam) -> float:
    lms = slam.landmarks()
    if not lms:
        return float("nan")
    err = [np.sum((est - world.landmarks[lid]) ** 2) for lid, est in lms.items()]
    return float(math.sqrt(np.mean(err)))


# --- the three simulations --------------------------------------------------------------------


def sim1(seed: int, cfg: EkfSlamConfig, pcfg: RecoveryPlannerConfig) -> dict:
    """Five loops around the landmark nearest the origin."""
    rng = np.random.default_rng(seed)
    world = make_world(rng)
    ref = int(np.argmin(np.hypot(world.landmarks[:, 0], world.landmarks[:, 1])))
    centre_true = world.landmarks[ref, :2]
    radius = pcfg.circle_radius_factor * pcfg.footprint_radius_m
    alpha0 = math.pi  # start south of the landmark, flying clockwise (seen from above)
    start = centre_true + radius * np.array([math.cos(alpha0), math.sin(alpha0)])
    vehicle, slam = _start(rng, cfg, np.array([start[0], start[1], wrap(alpha0 + math.pi / 2)]))
    centre = centre_true.copy()  # the vehicle circles its estimate of the landmark once it has one
    swept, last, loop = 0.0, alpha0, 0
    sq: list[float] = []
    per_loop_rms, per_loop_map, per_loop_end = [], [], []
    nees_trace = []
    carrot = (float(start[0]), float(start[1]))
    k = 0
    while loop < SIM1_LOOPS and k * DT_S < MAX_TIME_S:
        if k % OBSERVE_EVERY == 0:
            slam.update(sense(world, vehicle.pose, cfg, rng))
            if ref in slam.slot:
                centre = slam.x[slam.slot[ref]:slam.slot[ref] + 2].copy()
            rel = slam.x[:2] - centre
            ang = math.atan2(rel[1], rel[0]) + pcfg.lookahead_m / radius
            carrot = (float(centre[0] + radius * math.cos(ang)), float(centre[1] + radius * math.sin(ang)))
            sq.append(_horizontal_error(vehicle, slam) ** 2)
            nees_trace.append(nees(pose_error(vehicle.pose, slam.x), slam.pose_cov))
        v_m, w_m = vehicle.move(vehicle.steer(slam.x, carrot))
        slam.predict(v_m, w_m, DT_S)
        k += 1
        rel_true = vehicle.pose[:2] - centre_true
        a = math.atan2(rel_true[1], rel_true[0])
        swept += wrap(a - last)
        last = a
        if swept >= 2 * math.pi * (loop + 1):
            loop += 1
            per_loop_rms.append(math.sqrt(float(np.mean(sq))))
            per_loop_map.append(_map_rms(world, slam))
            per_loop_end.append(_horizontal_error(vehicle, slam))
            sq = []
    return {"vehicle_rms_per_loop_m": per_loop_rms, "map_rms_per_loop_m": per_loop_map,
            "error_at_loop_end_m": per_loop_end, "final_rms_m": per_loop_rms[-1] if per_loop_rms else float("nan"),
            "landmarks_mapped": slam.n_landmarks, "nees": nees_trace}


def sim2(seed: int, cfg: EkfSlamConfig) -> dict:
    """Dead reckoning only, straight from the jam point to the base."""
    rng = np.random.default_rng(seed)
    make_world(rng)  # the same draws as the other simulations for this seed
    heading = math.atan2(BASE_NE[1], BASE_NE[0])
    vehicle, slam = _start(rng, cfg, np.array([0.0, 0.0, heading]))
    base = np.array(BASE_NE)
    k = 0
    while np.hypot(*(slam.x[:2] - base)) > 1.0 and k * DT_S < MAX_TIME_S:
        v_m, w_m = vehicle.move(vehicle.steer(slam.x, BASE_NE))
        slam.predict(v_m, w_m, DT_S)
        k += 1
    return {"base_error_m": _horizontal_error(vehicle, slam), "time_s": k * DT_S,
            "nees_at_base": nees(pose_error(vehicle.pose, slam.x), slam.pose_cov)}


def sim3(seed: int, cfg: EkfSlamConfig, pcfg: RecoveryPlannerConfig) -> dict:
    """The proposed recovery: planner + EKF-SLAM with sub-maps, from the jam point to the base."""
    rng = np.random.default_rng(seed)
    world = make_world(rng)
    heading = math.atan2(BASE_NE[1], BASE_NE[0])
    vehicle, slam = _start(rng, cfg, np.array([0.0, 0.0, heading]))
    planner = RecoveryPlanner(pcfg, BASE_NE)
    nees_trace, rejected = [], 0
    out = None
    k = 0
    while k * DT_S < MAX_TIME_S:
        if k % OBSERVE_EVERY == 0:
            frame = sense(world, vehicle.pose, cfg, rng)
            result = slam.update(frame)
            rejected += len(result.rejected)
            mapped = slam.landmarks()
            in_view = {i: mapped[i] for i in frame if i in mapped}
            out = planner.target(k * DT_S, slam.x, in_view, mapped)
            if out.new_submap:
                slam.start_submap(out.keep_landmark, also_keep=out.also_keep)
            nees_trace.append(nees(pose_error(vehicle.pose, slam.x), slam.pose_cov))
            if out.kind in ("land", "hold"):
                break
        assert out is not None
        v_m, w_m = vehicle.move(vehicle.steer(slam.x, out.carrot_ne))
        slam.predict(v_m, w_m, DT_S)
        k += 1
    landed = out is not None and out.kind == "land"
    return {"base_error_m": _horizontal_error(vehicle, slam), "landed": landed,
            "landing_miss_m": float(np.hypot(*(vehicle.pose[:2] - np.array(BASE_NE)))),
            "time_s": k * DT_S, "distance_m": vehicle.distance_m, "submaps": planner.submaps,
            "circles": planner.circles, "gate_rejections": rejected, "nees": nees_trace,
            "final": out.kind if out else None}


# --- Monte-Carlo over the seeds ---------------------------------------------------------------


def nees_summary(traces: list[list[float]], dof: int = 3) -> dict:
    """Average NEES over the runs at each 5 Hz sample while at least half the runs still fly;
    the fraction of samples inside the 95 % band for the number of runs averaged there."""
    if not traces:
        return {}
    length = max(len(t) for t in traces)
    inside = total = 0
    means = []
    for i in range(length):
        values = [t[i] for t in traces if i < len(t)]
        if len(values) * 2 < len(traces) or not values:
            break
        m = float(np.mean(values))
        lo, hi = nees_band(dof, len(values))
        inside += lo <= m <= hi
        total += 1
        means.append(m)
    lo, hi = nees_band(dof, len(traces))
    return {"in_band_fraction": inside / total if total else float("nan"), "samples": total,
            "mean_nees": float(np.mean(means)) if means else float("nan"),
            "above_band_fraction": float(np.mean([m > nees_band(dof, len(traces))[1] for m in means])) if means else float("nan"),
            "band_95_all_runs": [lo, hi]}


def _median(values: list[float]) -> float:
    v = [x for x in values if x is not None and math.isfinite(x)]
    return float(np.median(v)) if v else float("nan")


def run_experiment(seeds: list[int], variant: str = "reference", progress: bool = True,
                   submap_keep: str = "in_view") -> dict:
    """All three simulations on ``seeds``; the report (module docstring)."""
    t0 = time.monotonic()
    cfg = EkfSlamConfig(consistency="fej", gnss_bias_sigma_m=0.0)  # the seed's simulations have no GNSS
    plain = replace(cfg, consistency="plain")
    pcfg = RecoveryPlannerConfig(variant="larger_loop" if variant == "larger-loop" else "reference",
                                 submap_keep=submap_keep)
    s1, s2, s3, b3 = [], [], [], []
    for n, seed in enumerate(seeds):
        s1.append(sim1(seed, cfg, RecoveryPlannerConfig()))
        s2.append(sim2(seed, cfg))
        s3.append(sim3(seed, cfg, pcfg))
        b3.append(sim3(seed, plain, pcfg))
        if progress:
            print(f"slam-recovery: seed {seed} ({n + 1}/{len(seeds)}): sim1 {s1[-1]['final_rms_m']:.2f} m, "
                  f"sim2 {s2[-1]['base_error_m']:.1f} m, sim3 {s3[-1]['base_error_m']:.2f} m "
                  f"(plain {b3[-1]['base_error_m']:.2f} m), {time.monotonic() - t0:.0f} s", file=sys.stderr)
    n3, nb = nees_summary([r["nees"] for r in s3]), nees_summary([r["nees"] for r in b3])
    n1 = nees_summary([r["nees"] for r in s1])
    loops = [[r["vehicle_rms_per_loop_m"][i] if i < len(r["vehicle_rms_per_loop_m"]) else float("nan") for r in s1]
             for i in range(SIM1_LOOPS)]
    maps = [[r["map_rms_per_loop_m"][i] if i < len(r["map_rms_per_loop_m"]) else float("nan") for r in s1]
            for i in range(SIM1_LOOPS)]
    report = {
        "sim1_final_rms_m": _median([r["final_rms_m"] for r in s1]),
        "sim2_base_error_m": _median([r["base_error_m"] for r in s2]),
        "sim3_base_error_m": _median([r["base_error_m"] for r in s3 if r["landed"]]),
        "sim3_nees_in_band_fraction": n3.get("in_band_fraction", float("nan")),
        "baseline_sim3_base_error_m": _median([r["base_error_m"] for r in b3 if r["landed"]]),
        "baseline_sim3_landed_fraction": float(np.mean([r["landed"] for r in b3])),
        "baseline_sim3_nees_in_band_fraction": nb.get("in_band_fraction", float("nan")),
        "sim1_vehicle_rms_per_loop_m": [_median(v) for v in loops],
        "sim1_map_rms_per_loop_m": [_median(v) for v in maps],
        "sim1_nees": n1,
        "sim2_base_error_p90_m": float(np.percentile([r["base_error_m"] for r in s2], 90)),
        "sim3_base_error_p90_m": float(np.percentile([r["base_error_m"] for r in s3], 90)),
        "sim3_landing_miss_m": _median([r["landing_miss_m"] for r in s3]),
        "sim3_landed_fraction": float(np.mean([r["landed"] for r in s3])),
        "sim3_flight_time_s": _median([r["time_s"] for r in s3]),
        "sim3_distance_m": _median([r["distance_m"] for r in s3]),
        "sim3_submaps": _median([r["submaps"] for r in s3]),
        "sim3_nees": n3,
        "baseline_sim3_nees": nb,
        "seed_paper": SEED_PAPER,
        "seeds": seeds,
        "variant": variant,
        "submap_keep": submap_keep,
        "per_seed": [{"seed": seed, "sim1_final_rms_m": a["final_rms_m"], "sim2_base_error_m": b["base_error_m"],
                      "sim3_base_error_m": c["base_error_m"], "sim3_landing_miss_m": c["landing_miss_m"],
                      "sim3_time_s": c["time_s"], "sim3_final": c["final"], "sim3_gate_rejections": c["gate_rejections"],
                      "baseline_sim3_base_error_m": d["base_error_m"]}
                     for seed, a, b, c, d in zip(seeds, s1, s2, s3, b3)],
        "settings": {"filter": asdict(cfg), "planner": asdict(pcfg), "speed_mps": SPEED_MPS, "dt_s": DT_S,
                     "observe_hz": 1.0 / (DT_S * OBSERVE_EVERY), "landmark_density_per_km2": DENSITY_PER_KM2,
                     "area_ne_m": AREA_NE, "base_ne_m": BASE_NE, "initial_sigma": INITIAL_SIGMA},
        "wall_time_s": time.monotonic() - t0,
    }
    return report


def run_slam_recovery(args: argparse.Namespace) -> int:
    """The CLI command: run, write ``args.out``, print the headline figures."""
    seeds = list(range(args.seed, args.seed + args.seeds))
    report = run_experiment(seeds, variant=args.variant, submap_keep=getattr(args, "submap_keep", "in_view"))
    Path(args.out).write_text(json.dumps(report, indent=2) + "\n")
    keys = ("sim1_final_rms_m", "sim2_base_error_m", "sim3_base_error_m", "sim3_nees_in_band_fraction",
            "baseline_sim3_base_error_m", "baseline_sim3_nees_in_band_fraction", "wall_time_s")
    print(json.dumps({k: report[k] for k in keys}, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    p = argparse.ArgumentParser()
    p.add_argument("--seeds", type=int, default=30)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    p.add_argument("--variant", choices=["reference", "larger-loop"], default="reference")
    p.add_argument("--submap-keep", choices=["in_view", "start"], default="in_view")
    sys.exit(run_slam_recovery(p.parse_args()))
