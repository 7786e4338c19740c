"""The three-laser-dot pose (companion/nav/laser_dots/geometry.py) and the beam calibration
(calibrate.py), on dots made by BeamRig.floor_hits from known poses (NED, floor z = 0)."""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import numpy as np
import pytest
import yaml

from companion.frames import euler_from_rotation, rotation_from_euler, wrap_pi
from companion.nav.laser_dots import geometry as g
from companion.laser_beams import BeamRig, BeamRigConfig, nominal_rig
from companion.nav.laser_dots.calibrate import calibrate_beams, rig_to_yaml

POSES = 300


def offset_rig() -> BeamRig:
    """90-degree directions from three origins about 5 cm apart (a real mount), body FRD m."""
    ideal = nominal_rig(90.0, 10.0)
    origins = np.array([[0.05, 0.0, 0.01], [-0.02, 0.04, 0.0], [-0.02, -0.03, 0.02]])
    return BeamRig(origins, ideal.directions)


RIGS = {"90deg": nominal_rig(90.0, 10.0), "89deg": nominal_rig(89.0, 10.0), "60deg": nominal_rig(60.0, 10.0),
        "origins-5cm-apart": offset_rig()}


def random_pose(rng: np.random.Generator, max_tilt_deg: float = 20.0,
                heights: tuple[float, float] = (0.5, 2.5)) -> tuple[np.ndarray, np.ndarray]:
    """Rotation body -> NED (roll, pitch within +-max_tilt_deg, any yaw) and NED position m."""
    roll, pitch = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
    rotation = rotation_from_euler(roll, pitch, rng.uniform(-math.pi, math.pi))
    return rotation, np.array([*rng.uniform(-5.0, 5.0, 2), -rng.uniform(*heights)])


def dots_of(rig: BeamRig, rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    points, lengths = rig.floor_hits(rotation, position)
    assert np.all(np.isfinite(lengths))
    return points[:, :2]


def imu_like(rotation: np.ndarray, rng: np.random.Generator, sigma_deg: float = 2.0) -> np.ndarray:
    """The rotation with a few degrees of error, as an IMU attitude prior."""
    return rotation_from_euler(*np.radians(rng.normal(0.0, sigma_deg, 3))) @ rotation


def pose_error(rotation: np.ndarray, position: np.ndarray, solution: g.PoseSolution) -> tuple[float, float]:
    return float(np.linalg.norm(solution.position_ned - position)), g.rotation_angle(solution.rotation, rotation)


# --- the seed's closed form -------------------------------------------------------------------

def test_closed_form_is_exact_on_the_ideal_90_degree_rig() -> None:
    rig, rng = nominal_rig(90.0, 25.0), np.random.default_rng(1)
    for _ in range(POSES):
        rotation, position = random_pose(rng)
        points, true_lengths = rig.floor_hits(rotation, position)
        lengths, origin = g.closed_form_90(points[:, :2])
        assert np.abs(lengths - true_lengths).max() < 1e-9 and np.abs(origin - position).max() < 1e-9
        solution = g.solve(rig, points[:, :2], "closed_form")
        assert solution is not None
        assert max(pose_error(rotation, position, solution)) < 1e-9


def test_closed_form_has_no_solution_for_impossible_or_collinear_dots() -> None:
    obtuse = np.array([[0.0, 0.0], [1.0, 0.1], [-1.0, 0.1]])  # l1^2 = (a1^2 - a2^2 + a3^2) / 2 < 0
    collinear = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    assert g.closed_form_90(obtuse) is None and g.closed_form_90(collinear) is None
    assert g.solve(nominal_rig(), obtuse, "closed_form") is None


def test_closed_form_refuses_a_rig_far_from_90_degrees() -> None:
    rig = nominal_rig(60.0)
    with pytest.raises(ValueError, match="method='general'"):
        g.solve(rig, dots_of(rig, np.eye(3), np.array([0.0, 0.0, -1.0])), "closed_form")


@pytest.mark.parametrize("rig", [nominal_rig(90.0), nominal_rig(60.0, 40.0), offset_rig()], ids=["90", "60", "offset"])
def test_attitude_from_beams_recovers_the_rotation(rig: BeamRig) -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        rotation, position = random_pose(rng)
        points, lengths = rig.floor_hits(rotation, position)
        found = g.attitude_from_beams(rig, lengths, points[:, :2], position)
        assert g.rotation_angle(found, rotation) < 1e-9


def test_euler_angles_invert_the_zyx_rotation_and_seed_eq_29_is_its_transpose() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        roll, pitch, yaw = rng.uniform(-1.4, 1.4), rng.uniform(-1.4, 1.4), rng.uniform(-3.1, 3.1)
        rotation = rotation_from_euler(roll, pitch, yaw)
        assert np.allclose(euler_from_rotation(rotation), (roll, pitch, yaw), atol=1e-12)
        c, s = np.cos((roll, pitch, yaw)), np.sin((roll, pitch, yaw))
        eq29 = np.array([  # the seed's R_e^b (NED -> body) of angles phi, theta, psi
            [c[1] * c[2], c[1] * s[2], -s[1]],
            [-c[0] * s[2] + s[0] * s[1] * c[2], c[0] * c[2] + s[0] * s[1] * s[2], s[0] * c[1]],
            [s[0] * s[2] + c[0] * s[1] * c[2], -s[0] * c[2] + c[0] * s[1] * s[2], c[0] * c[1]]])
        assert np.allclose(eq29, rotation.T, atol=1e-12)


# --- general angles ---------------------------------------------------------------------------

@pytest.mark.parametrize("name", list(RIGS))
def test_general_solver_recovers_every_random_pose(name: str) -> None:
    rig, rng = RIGS[name], np.random.default_rng(4)
    for _ in range(POSES):
        rotation, position = random_pose(rng)
        solution = g.solve(rig, dots_of(rig, rotation, position), "general", prior_rotation=imu_like(rotation, rng))
        assert solution is not None
        position_error, angle_error = pose_error(rotation, position, solution)
        assert position_error < 1e-6 and angle_error < 1e-6
        assert np.allclose(solution.euler_rad, euler_from_rotation(rotation), atol=1e-6)
        assert solution.cross_check_deg < 1e-6


@pytest.mark.parametrize("name", ["90deg", "origins-5cm-apart"])
def test_at_90_degrees_the_solution_is_unique_without_a_prior(name: str) -> None:
    """Grunert's quartic has double roots here (a root finder's tiny imaginary parts): none is lost."""
    rig, rng = RIGS[name], np.random.default_rng(5)
    for _ in range(POSES):
        rotation, position = random_pose(rng)
        candidates = g.p3p_candidates(rig, dots_of(rig, rotation, position))
        assert len(candidates) == 1
        assert np.linalg.norm(candidates[0].position_ned - position) < 1e-6


def test_an_89_degree_rig_taken_for_90_errs_by_centimetres_until_calibrated() -> None:
    rig, rng = nominal_rig(89.0, 10.0), np.random.default_rng(6)
    closed, general = [], []
    for _ in range(100):
        rotation, position = random_pose(rng, heights=(1.0, 2.0))
        dots = dots_of(rig, rotation, position)
        closed.append(pose_error(rotation, position, g.solve(rig, dots, "closed_form")))
        general.append(pose_error(rotation, position, g.solve(rig, dots, "general", imu_like(rotation, rng))))
    position_m, angle_rad = np.median(closed, axis=0)
    assert 0.01 < position_m < 0.1  # REFERENCE: ~4 cm
    assert 0.1 < math.degrees(angle_rad) < 1.0  # REFERENCE: ~0.3 deg
    assert np.max(general) < 1e-6


# --- selection --------------------------------------------------------------------------------

def test_selection_rejects_upside_down_below_floor_and_backward_candidates() -> None:
    rotation, position = rotation_from_euler(0.1, -0.05, 1.0), np.array([1.0, 2.0, -1.2])
    lengths = np.array([1.5, 1.6, 1.7])
    true = g.PoseCandidate(rotation, position, lengths, 0.0)
    upside_down = g.PoseCandidate(rotation @ np.diag([1.0, -1.0, -1.0]), position, lengths, 0.0)
    below = g.PoseCandidate(rotation, position * [1.0, 1.0, -1.0], lengths, 0.0)
    backward = g.PoseCandidate(rotation, position, -lengths, 0.0)
    tilted = g.PoseCandidate(rotation_from_euler(0.9, 0.0, 0.0), position, lengths, 0.0)
    chosen, reason = g.select_candidate([upside_down, below, true, backward, tilted])
    assert chosen is true and reason == "the only plausible candidate"
    chosen, reason = g.select_candidate([upside_down, below, backward, tilted])
    assert chosen is None
    assert "2 tilted beyond 45 deg" in reason and "1 with a beam starting less than 0.05 m above the floor" in reason
    assert "1 with a beam pointing backwards" in reason


def two_plausible_poses() -> tuple[BeamRig, np.ndarray, np.ndarray, np.ndarray]:
    """A 60-degree rig and a pose whose dots another plausible pose also explains."""
    rig, rng = RIGS["60deg"], np.random.default_rng(7)
    for _ in range(POSES):
        rotation, position = random_pose(rng)
        dots = dots_of(rig, rotation, position)
        plausible = [c for c in g.p3p_candidates(rig, dots)
                     if c.position_ned[2] < -0.05 and g.tilt_rad(c.rotation) < math.radians(45.0)]
        if len(plausible) > 1:
            return rig, dots, rotation, position
    raise AssertionError("no ambiguous pose found")


def test_selection_needs_a_prior_when_two_poses_explain_the_dots() -> None:
    rig, dots, rotation, position = two_plausible_poses()
    chosen, reason = g.select_candidate(g.p3p_candidates(rig, dots))
    assert chosen is None and reason.startswith("ambiguous")
    assert g.solve(rig, dots) is None
    with_imu = g.solve(rig, dots, prior_rotation=imu_like(rotation, np.random.default_rng(8)))
    with_previous = g.solve(rig, dots, previous=(rotation_from_euler(0.02, 0.0, 0.03) @ rotation, position + 0.05))
    for solution in (with_imu, with_previous):
        assert solution is not None and len(solution.candidates) > 1
        assert max(pose_error(rotation, position, solution)) < 1e-6


# --- covariance -------------------------------------------------------------------------------

@pytest.mark.parametrize("angle, method", [(90.0, "closed_form"), (60.0, "general")])
def test_covariance_matches_the_scatter_of_noisy_solutions(angle: float, method: g.Method) -> None:
    rig = nominal_rig(angle, 10.0)
    rotation, position = rotation_from_euler(0.15, -0.1, 2.0), np.array([1.0, -0.5, -1.6])
    dots = dots_of(rig, rotation, position)
    sigma = np.array([0.003, 0.0045])  # north, east m
    solution = g.solve(rig, dots, method, prior_rotation=rotation)
    covariance = g.pose_covariance(rig, dots, np.tile(np.diag(sigma ** 2), (3, 1, 1)), method, solution)
    rng, errors = np.random.default_rng(9), []
    for _ in range(2000):
        noisy = g.solve(rig, dots + rng.normal(0.0, 1.0, (3, 2)) * sigma, method, prior_rotation=rotation)
        errors.append(np.concatenate((noisy.position_ned - position, wrap_pi(noisy.euler_rad - solution.euler_rad))))
    ratio = np.diag(np.cov(np.array(errors).T)) / np.diag(covariance)
    assert np.all(np.abs(ratio - 1.0) < 0.2), ratio


def test_general_covariance_jacobian_equals_central_differences_of_the_solver() -> None:
    rig = nominal_rig(80.0, 10.0)
    rotation, position = rotation_from_euler(0.2, -0.15, 2.5), np.array([0.4, 1.1, -1.3])
    dots = dots_of(rig, rotation, position)
    solution = g.solve(rig, dots, "general", prior_rotation=rotation)

    def solved(x: np.ndarray) -> np.ndarray:
        return np.array([np.concatenate((s.position_ned, s.euler_rad)) for s in
                         (g.solve(rig, d.reshape(3, 2), "general", prior_rotation=rotation) for d in x)])
    numeric = g._central_jacobian(solved, dots.ravel(), slice(3, 6), step=1e-5)
    assert np.allclose(g._general_jacobian(rig, solution), numeric, atol=1e-6)


def test_covariance_is_unknown_when_the_solver_fails_next_to_the_dots() -> None:
    rig = nominal_rig(90.0)
    dots = dots_of(rig, np.eye(3), np.array([0.0, 0.0, -1.0]))
    solution = g.solve(rig, dots, "closed_form")
    collinear = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]])
    assert np.all(np.isnan(g.pose_covariance(rig, collinear, np.tile(np.eye(2), (3, 1, 1)), "closed_form", solution)))


# --- structured light -------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["60deg", "origins-5cm-apart"])
def test_floor_plane_in_the_body_gives_height_roll_and_pitch(name: str) -> None:
    rig, rng = RIGS[name], np.random.default_rng(10)
    for _ in range(100):
        rotation, position = random_pose(rng)
        _, lengths = rig.floor_hits(rotation, position)
        height, roll, pitch = g.plane_from_body_points(g.dots_in_body(rig, lengths))
        true_roll, true_pitch, _ = euler_from_rotation(rotation)
        assert abs(height + position[2]) < 1e-9 and abs(roll - true_roll) < 1e-9 and abs(pitch - true_pitch) < 1e-9


def test_height_covariance_matches_the_scatter_of_noisy_lengths() -> None:
    rig = offset_rig()
    _, lengths = rig.floor_hits(rotation_from_euler(0.2, -0.1, 0.3), np.array([0.0, 0.0, -1.3]))
    variances = np.array([0.004, 0.006, 0.005]) ** 2
    covariance = g.height_covariance(rig, lengths, variances)
    rng = np.random.default_rng(11)
    base = np.array(g.plane_from_body_points(g.dots_in_body(rig, lengths)))
    samples = [np.array(g.plane_from_body_points(g.dots_in_body(rig, lengths + rng.normal(0.0, np.sqrt(variances)))))
               - base for _ in range(2000)]
    ratio = np.diag(np.cov(np.array(samples).T)) / np.diag(covariance)
    assert np.all(np.abs(ratio - 1.0) < 0.2), ratio


# --- calibration ------------------------------------------------------------------------------

def true_mount() -> BeamRig:
    """An 89-degree rig built a little off: each beam turned ~1 deg, origins 2-3 cm apart."""
    nominal, rng = nominal_rig(89.0, 10.0), np.random.default_rng(12)
    directions = [rotation_from_euler(*np.radians(rng.normal(0.0, 0.7, 3))) @ d for d in nominal.directions]
    return BeamRig(np.array([[0.02, 0.0, 0.01], [-0.01, 0.02, 0.0], [-0.01, -0.02, 0.015]]), np.array(directions))


def observations(rig: BeamRig, count: int, heights: tuple[float, float], seed: int = 13) -> list:
    """Frames at poses known to 1 mm and 0.03 deg (motion capture), dots to 1 mm, one dot in ten unseen."""
    rng, frames = np.random.default_rng(seed), []
    for _ in range(count):
        rotation, position = random_pose(rng, max_tilt_deg=10.0, heights=heights)
        dots = dots_of(rig, rotation, position) + rng.normal(0.0, 0.001, (3, 2))
        dots[rng.uniform(size=3) < 0.1] = np.nan
        known = rotation_from_euler(*np.radians(rng.normal(0.0, 0.03, 3))) @ rotation
        frames.append((known, position + rng.normal(0.0, 0.001, 3), dots))
    return frames


def test_calibration_recovers_beam_directions_and_origins() -> None:
    true, nominal = true_mount(), nominal_rig(90.0, 10.0)
    result = calibrate_beams(observations(true, 30, (0.6, 1.8)), nominal)
    for i in range(3):
        along = (nominal.origins[i] - true.origins[i]) @ true.directions[i]
        expected_origin = true.origins[i] + along * true.directions[i]  # true line's point nearest the nominal origin
        assert np.degrees(np.arccos(min(1.0, result.rig.directions[i] @ true.directions[i]))) < 0.1
        assert np.linalg.norm(result.rig.origins[i] - expected_origin) < 0.005
    assert np.all(result.count >= 20) and np.all(result.rms_m < 0.005)
    assert np.allclose(result.angles_deg, [true.angle_deg(0, 1), true.angle_deg(1, 2), true.angle_deg(0, 2)], atol=0.2)
    loaded = BeamRigConfig(**yaml.safe_load(rig_to_yaml(result.rig))["beams"]).rig()
    assert np.abs(loaded.origins - result.rig.origins).max() < 1e-6
    assert np.abs(loaded.directions - result.rig.directions).max() < 1e-5


def test_calibrated_rig_makes_the_general_solver_accurate_on_the_real_mount() -> None:
    true = true_mount()
    calibrated = calibrate_beams(observations(true, 30, (0.6, 1.8)), nominal_rig(90.0, 10.0)).rig
    nominal, rng, errors, nominal_errors = nominal_rig(90.0, 10.0), np.random.default_rng(14), [], []
    for _ in range(50):
        rotation, position = random_pose(rng, heights=(1.0, 2.0))
        dots, prior = dots_of(true, rotation, position), imu_like(rotation, rng)
        errors.append(pose_error(rotation, position, g.solve(calibrated, dots, prior_rotation=prior)))
        nominal_errors.append(pose_error(rotation, position, g.solve(nominal, dots, prior_rotation=prior)))
    position_m, angle_rad = np.max(errors, axis=0)
    assert position_m < 0.005 and math.degrees(angle_rad) < 0.1
    assert np.median(nominal_errors, axis=0)[0] > 0.02  # the mount as designed: centimetres off


def test_calibration_refuses_too_few_or_too_flat_observations() -> None:
    true, nominal = true_mount(), nominal_rig(90.0, 10.0)
    with pytest.raises(ValueError, match="beam 0: 2 frames saw its dot"):
        calibrate_beams([(np.eye(3), np.array([0.0, 0.0, -h]), dots_of(true, np.eye(3), np.array([0.0, 0.0, -h])))
                         for h in (0.8, 1.5)], nominal)
    with pytest.raises(ValueError, match=r"span 0\.\d\d m of height, at least 0.3 m"):
        calibrate_beams(observations(true, 30, (1.0, 1.2)), nominal)


# --- field of view ----------------------------------------------------------------------------

def pinhole(focal_px: float, width: int, height: int) -> Callable[[np.ndarray], np.ndarray]:
    """Body points (N, 3) m -> pixels (N, 2) of a camera at the body origin looking down: image
    right = body right, image up = body forward."""
    def project(p: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.where(p[:, 2] > 0, width / 2 + focal_px * p[:, 1] / p[:, 2], np.nan)
            v = np.where(p[:, 2] > 0, height / 2 - focal_px * p[:, 0] / p[:, 2], np.nan)
        return np.column_stack((u, v))
    return project


def test_seed_field_of_view_formulas_invert_each_other() -> None:
    assert g.seed_min_sensor_ratio(90.0) == pytest.approx(2.0 * math.sqrt(2.0))
    for angle in (30.0, 60.0, 90.0, 110.0):
        assert g.seed_max_beam_angle_deg(g.seed_min_sensor_ratio(angle)) == pytest.approx(angle)


@pytest.mark.parametrize("scale, in_view", [(1.02, True), (0.98, False)])
def test_fov_check_agrees_with_seed_eq_41_for_a_camera_at_the_beams_origin(scale: float, in_view: bool) -> None:
    rig, size = nominal_rig(90.0, 0.0), 400  # beam 0 towards the image's top edge
    focal = size / (scale * g.seed_min_sensor_ratio(90.0))  # sensor / focal = scale * the seed's minimum
    problems = g.fov_problems(rig, pinhole(focal, size, size), size, size, (0.5, 2.0), 20.0, margin_px=0.0)
    assert (problems == []) == in_view


def leaning(tilt_deg: float, towards_deg: float) -> np.ndarray:
    """Up axis tilted towards an azimuth at zero yaw: pitch nose-down seen from that azimuth."""
    turn = rotation_from_euler(0.0, 0.0, math.radians(towards_deg))
    return turn @ rotation_from_euler(0.0, -math.radians(tilt_deg), 0.0) @ turn.T


def test_fov_problems_name_the_beam_and_the_pose_that_lose_a_dot() -> None:
    rig = nominal_rig(90.0, 0.0, (0.1, 0.0, 0.0))  # beams 10 cm ahead of the camera: parallax
    assert g.fov_problems(rig, pinhole(80.0, 640, 480), 640, 480, (0.5, 2.0), 15.0) == []
    project = pinhole(140.0, 640, 480)
    problems = g.fov_problems(rig, project, 640, 480, (0.5, 2.0), 15.0)
    assert problems
    pattern = re.compile(r"at ([\d.]+) m height and ([\d.]+) deg tilt towards ([\d.]+) deg, beam (\d)'s dot is outside")
    for problem in problems:
        h, tilt, towards, beam = pattern.match(problem).groups()
        _, lengths = rig.floor_hits(leaning(float(tilt), float(towards)), np.array([0.0, 0.0, -float(h)]))
        u, v = project(g.dots_in_body(rig, lengths))[int(beam)]
        assert not (5 <= u <= 635 and 5 <= v <= 475)
    assert not any("2 m height" in p or "level" in p for p in problems)  # only low and tilted
