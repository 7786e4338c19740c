"""Settings of the EKF-SLAM and of the recovery planner (``companion.schema`` dataclasses), shared
by the ``ekf_slam`` pipeline (companion/nav/ekf_slam/pipeline.py), the simulation and the tests:
the seed's Table 1 (Lee and Tahk 2010) for the sensor and the motion input, its Sec. 4 for the
planner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from companion.schema import meta


@dataclass
class EkfSlamConfig:
    altitude_m: float = field(default=100.0, metadata=meta(
        "Held altitude above the ground datum (m, up; the vehicle's NED down is -altitude_m).", (1.0, 2000.0)))
    sigma_v_mps: float = field(default=0.2, metadata=meta(
        "Standard deviation of the speed input per motion step (m/s; seed Table 1, at 40 Hz; the daemon's steps are "
        "its IMU samples).", (0.0, 10.0)))
    sigma_omega_dps: float = field(default=2.5, metadata=meta(
        "Standard deviation of the yaw-rate input per motion step (deg/s): Table 1's 2 deg steering "
        "noise through Bailey's 4 m wheelbase at 5 m/s (see ekf_slam/model.py).", (0.0, 90.0)))
    sigma_range_m: float = field(default=0.2, metadata=meta(
        "Standard deviation of a landmark's range (m; seed Table 1), for frames whose sensor states none (the SLAM "
        "weighs a frame with the noise its sensor states).", (1e-4, 100.0)))
    sigma_azimuth_deg: float = field(default=0.16, metadata=meta(
        "Standard deviation of a landmark's azimuth (deg; seed Table 1 'yaw bearing'), for frames stating none.", (1e-4, 30.0)))
    sigma_elevation_deg: float = field(default=0.12, metadata=meta(
        "Standard deviation of a landmark's elevation (deg; seed Table 1 'pitch bearing'), for frames stating none.", (1e-4, 30.0)))
    half_fov_deg: float = field(default=20.0, metadata=meta(
        "Half angle of the downward sensor's field of view (deg; a cone about the nadir).", (1.0, 89.0)))
    min_horizontal_m: float = field(default=4.0, metadata=meta(
        "Landmarks seen closer than this to the nadir (horizontal distance, m) update the filter as their offset "
        "(forward, right, down) in the heading frame instead of range / azimuth / elevation (the azimuth is singular "
        "there and its linearisation wrong by more than its noise); new ones are not added there.", (0.0, 100.0)))
    gate_chi2: float = field(default=16.27, metadata=meta(
        "Innovation gate: squared Mahalanobis distance (3 degrees of freedom; 16.27 = 99.9 %).", (1.0, 1000.0)))
    moved_after: int = field(default=5, metadata=meta(
        "A landmark rejected by the gate this many frames in a row, while others of its frames were accepted, is "
        "taken as moved and no longer used.", (1, 1000)))
    lost_after_frames: int = field(default=3, metadata=meta(
        "Frames in a row in which the gate refused known landmarks and accepted no more: the vehicle is lost "
        "against its map, and from then on its position covariance is inflated each such frame (sigma about "
        "doubled, at most 50 m).",
        (1, 1000)))
    gnss_bias_sigma_m: float = field(default=0.5, metadata=meta(
        "GNSS bias states: 1-sigma per axis of the slowly wandering part of a fix's error (multipath, atmosphere), "
        "metres; the fix then measures position plus bias. Fixes fused as white noise would make the vehicle and "
        "the map they anchor claim centimetres, and a landmark seen again after the return (the landing pad) be "
        "refused as moved. 0: no bias states (fixes as white noise).", (0.0, 100.0)))
    gnss_bias_tau_s: float = field(default=60.0, metadata=meta(
        "Correlation time of the GNSS bias (first-order Gauss-Markov), seconds.", (1.0, 100000.0)))
    consistency: Literal["fej", "plain"] = field(default="fej", metadata=meta(
        "fej: first-estimates Jacobians (Huang, Mourikis, Roumeliotis 2008/2010); plain: the textbook "
        "EKF-SLAM of the seed (over-confident as the heading uncertainty grows)."))

    @property
    def down_m(self) -> float:
        """The vehicle's NED down coordinate (m)."""
        return -self.altitude_m

    def r_matrix(self) -> list[float]:
        """Diagonal of the observation noise covariance (range m^2, azimuth rad^2, elevation rad^2)."""
        return [self.sigma_range_m ** 2, math.radians(self.sigma_azimuth_deg) ** 2,
                math.radians(self.sigma_elevation_deg) ** 2]

    def q_matrix(self) -> list[float]:
        """Diagonal of the motion input noise covariance (speed (m/s)^2, yaw rate (rad/s)^2)."""
        return [self.sigma_v_mps ** 2, math.radians(self.sigma_omega_dps) ** 2]


@dataclass
class RecoveryPlannerConfig:
    variant: Literal["reference", "larger_loop"] = field(default="reference", metadata=meta(
        "reference: circles centred on the reference landmark (seed Sec. 4 STEPs 3-4); larger_loop: "
        "circles of a larger radius not centred on a landmark (seed Figs. 7-8)."))
    altitude_m: float = field(default=100.0, metadata=meta(
        "Altitude the recovery flies at (m above the ground datum).", (1.0, 2000.0)))
    half_fov_deg: float = field(default=20.0, metadata=meta(
        "Half angle of the downward sensor's field of view (deg).", (1.0, 89.0)))
    circle_radius_factor: float = field(default=0.8, metadata=meta(
        "Circle radius around the reference landmark as a fraction of the footprint radius "
        "altitude * tan(half FOV) (below 1 keeps the landmark in view despite its height).", (0.1, 1.0)))
    larger_loop_factor: float = field(default=2.0, metadata=meta(
        "larger_loop variant: circle radius as a multiple of the footprint radius.", (1.0, 20.0)))
    loops: int = field(default=1, metadata=meta("Closed loops flown on each circle (seed STEP 5: at least one).",
                                                (1, 20)))
    clockwise: bool = field(default=True, metadata=meta("Fly the circles clockwise seen from above."))
    lookahead_m: float = field(default=10.0, metadata=meta(
        "Distance ahead along a circle of the point the vehicle steers to (m).", (0.5, 200.0)))
    on_circle_tolerance: float = field(default=0.3, metadata=meta(
        "Loops are counted once the vehicle is within this fraction of the radius of its circle.", (0.01, 1.0)))
    arrive_m: float = field(default=3.0, metadata=meta(
        "A goto point (the next start point) is reached within this horizontal distance (m).", (0.1, 100.0)))
    final_leg_m: float = field(default=50.0, metadata=meta(
        "When the base is this close (by the estimate, m) the vehicle flies straight to it.", (0.0, 1000.0)))
    land_radius_m: float = field(default=1.0, metadata=meta(
        "Land when the estimate is this close to the base (m, horizontal).", (0.05, 100.0)))
    submap_keep: Literal["in_view", "start"] = field(default="in_view", metadata=meta(
        "What a new sub-map keeps besides the vehicle: start = the start landmark only (the seed's STEP 6); "
        "in_view = also the landmarks in view there, with their covariances (they hold the heading)."))
    search_leg_m: float = field(default=30.0, metadata=meta(
        "Leg increment of the expanding-square search flown when no landmark is in view (m).", (1.0, 1000.0)))
    search_time_s: float = field(default=180.0, metadata=meta(
        "Give up the search after this long (s) and do on_search_timeout.", (1.0, 3600.0)))
    on_search_timeout: Literal["hold", "land"] = field(default="hold", metadata=meta(
        "What to do when the search found no landmark in search_time_s."))

    @property
    def footprint_radius_m(self) -> float:
        """Radius of the sensor's footprint on the ground datum (m): altitude * tan(half FOV)."""
        return self.altitude_m * math.tan(math.radians(self.half_fov_deg))

    @property
    def circle_radius_m(self) -> float:
        """Radius of the closed path of the chosen variant (m)."""
        factor = self.circle_radius_factor if self.variant == "reference" else self.larger_loop_factor
        return factor * self.footprint_radius_m
