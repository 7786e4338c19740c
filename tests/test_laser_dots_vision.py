"""The laser-dot pipeline's vision (companion/nav/laser_dots/detect.py and floor.py) on real OpenCV:
dots on synthetic BGR images drawn where the camera model puts each beam's floor hit, floor
markers on frames rendered by the simulated camera (sitl/camera_sim.py) from known poses."""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import cv2
import numpy as np
import pytest

from companion.calibration import CameraCalibration
from companion.config import MountConfig
from companion.frames import quat_from_euler, rotation_from_euler
from companion.laser_beams import nominal_rig
from companion.nav.laser_dots.detect import (GREY_REASON, SATURATED_REASON, DotDetector, Dots, best_assignment,
                                             triangulate)
from companion.nav.laser_dots.floor import FloorMapper, FloorView
from companion.world import Bounds, FloorMarker, World
from drivers.mount import OPTICAL_TO_SENSOR, Mount
from sitl.camera_sim import SimCameraSettings, SimulatedCamera

# -- laser dots ---------------------------------------------------------------------------------

CALIBRATION = CameraCalibration(640, 480, np.array([[262.0, 0.0, 321.3], [0.0, 261.0, 238.6], [0.0, 0.0, 1.0]]),
                                np.array([-0.08, 0.012, 0.0004, -0.0003, 0.0]))
MOUNT = Mount.from_config(MountConfig(position_m=(-0.05, 0.04, 0.03), rpy_deg=(0.0, -90.0, 0.0)))  # looking down
OPTICAL_TO_BODY = MOUNT.rotation @ OPTICAL_TO_SENSOR
RIG = nominal_rig(60.0, 20.0, (0.10, 0.0, 0.0))  # 16 cm from the camera: the baseline of the triangulation
# (position NED m, roll pitch yaw deg): the dots stay in view of the 100x85 degree lens
POSES = (((0.0, 0.0, -1.0), (0.0, 0.0, 0.0)), ((0.5, -0.3, -1.6), (8.0, -5.0, 30.0)),
         ((-1.0, 2.0, -0.6), (-10.0, 7.0, -120.0)), ((0.2, 0.1, -2.4), (4.0, 9.0, 170.0)))
BACKGROUND_SEED = 4


@dataclass(frozen=True)
class DotTruth:
    """Where the beams' dots are for one vehicle pose: (3, 2) pixels and (3,) beam lengths, m."""

    pixels: np.ndarray
    lengths_m: np.ndarray


def dot_truth(position: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> DotTruth:
    """The pixels of the beams' floor hits for a vehicle at ``position`` (NED) with attitude ``rpy_deg``."""
    body_to_ned = rotation_from_euler(*np.radians(rpy_deg))
    hits, lengths = RIG.floor_hits(body_to_ned, np.array(position))
    optical_to_ned = body_to_ned @ OPTICAL_TO_BODY
    centre = np.array(position) + body_to_ned @ MOUNT.offset_m
    return DotTruth(CALIBRATION.project((hits - centre) @ optical_to_ned), lengths)


def background(seed: int = BACKGROUND_SEED) -> np.ndarray:
    """(480, 640) float grey floor texture (blotches 60..160 grey levels), the same in B, G and R."""
    noise = np.random.default_rng(seed).uniform(0.0, 1.0, (60, 80)).astype(np.float32)
    return 60.0 + 100.0 * cv2.resize(noise, (640, 480), interpolation=cv2.INTER_CUBIC).clip(0.0, 1.0)


def draw_dots(pixels: np.ndarray, grey: np.ndarray | None = None) -> np.ndarray:
    """A BGR uint8 image of the floor ``grey`` with a laser dot at each (u, v) of ``pixels``: a
    Gaussian core (1.6 px) that saturates red and raises green and blue by crosstalk, in a faint
    red bloom (5 px)."""
    base = background() if grey is None else grey
    v, u = np.mgrid[0:480, 0:640].astype(float)
    red, other = base.copy(), base.copy()
    for pu, pv in pixels:
        r2 = (u - pu) ** 2 + (v - pv) ** 2
        core, bloom = np.exp(-r2 / (2 * 1.6 ** 2)), np.exp(-r2 / (2 * 5.0 ** 2))
        red += 420.0 * core + 70.0 * bloom
        other += 90.0 * core + 8.0 * bloom
    return np.dstack((other, other, red)).round().clip(0, 255).astype(np.uint8)


def detector() -> DotDetector:
    return DotDetector(CALIBRATION, OPTICAL_TO_BODY, MOUNT.offset_m, RIG)


def test_a_dot_washed_out_to_white_on_white_paper_is_still_found_at_its_centre() -> None:
    truth = dot_truth(*POSES[0])
    paper = np.full((480, 640), 235.0)  # white paper: the core saturates red and green, dominance ~0 there
    image = draw_dots(truth.pixels, paper)
    assert np.count_nonzero(np.all(image[..., 1:] == 255, axis=2)) > 10, "the test needs washed-out cores"
    dots = detector().detect(image)
    assert dots.found.all()
    assert np.max(np.linalg.norm(dots.pixels - truth.pixels, axis=1)) < 0.2


@pytest.mark.parametrize("position, rpy_deg", POSES)
def test_dot_centroids_are_within_a_seventh_of_a_pixel_with_the_right_beam(
        position: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> None:
    truth = dot_truth(position, rpy_deg)
    assert np.all((truth.pixels > 10) & (truth.pixels < [630, 470])), "the pose must keep the dots in view"
    dots = detector().detect(draw_dots(truth.pixels))
    assert dots.reason is None and dots.found.all() and dots.extra == 0
    assert np.abs(dots.pixels - truth.pixels).max() < 0.15, dots.pixels - truth.pixels


def test_the_beams_are_told_apart_by_their_curves_not_their_order_in_the_image() -> None:
    truth = dot_truth(*POSES[1])
    order = np.argsort(truth.pixels[:, 0])
    dots = detector().detect(draw_dots(truth.pixels[order]))  # drawn in another order than the beams'
    assert np.abs(dots.pixels - truth.pixels).max() < 0.15


@pytest.mark.parametrize("position, rpy_deg", POSES[:3])  # beams up to 2.2 m: with the 16 cm baseline a
def test_triangulated_beam_lengths_match_the_truth_to_a_few_millimetres(  # 0.1 px centroid error is ~1 cm at 3 m
        position: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> None:
    truth = dot_truth(position, rpy_deg)
    dots = detector().detect(draw_dots(truth.pixels))
    assert np.abs(dots.lengths_m - truth.lengths_m).max() < 0.005, dots.lengths_m - truth.lengths_m
    assert np.all(dots.miss_m < 0.002)


def test_triangulate_finds_the_beam_length_of_an_exact_ray_and_reports_the_miss() -> None:
    origin, direction, camera = np.array([0.1, 0.0, 0.0]), np.array([0.6, 0.2, 0.77]), np.array([-0.05, 0.04, 0.03])
    direction /= np.linalg.norm(direction)
    dot = origin + 1.7 * direction
    length, miss, point = triangulate(origin, direction, camera, 3.0 * (dot - camera))
    assert length == pytest.approx(1.7, abs=1e-9) and miss < 1e-9 and np.allclose(point, dot)
    side = np.cross(direction, dot - camera)
    side *= 0.01 / np.linalg.norm(side)  # the same ray moved 1 cm square to it and to the beam
    length, miss, _ = triangulate(origin, direction, camera + side, dot - camera)
    assert length == pytest.approx(1.7, abs=1e-6) and miss == pytest.approx(0.01, abs=1e-6)
    assert math.isnan(triangulate(origin, direction, camera, direction)[0])


def test_a_fourth_red_spot_off_the_curves_is_counted_extra_and_ignored() -> None:
    truth = dot_truth(*POSES[0])
    stray = truth.pixels[:1] + [25.0, 0.0]  # in beam 0's search window, off every curve
    assert detector().curve_distances(stray).min() > 8.0
    dots = detector().detect(draw_dots(np.vstack((truth.pixels, stray))))
    assert dots.extra == 1 and dots.found.all()
    assert np.abs(dots.pixels - truth.pixels).max() < 0.15


def test_a_red_spot_outside_every_search_window_is_not_even_seen() -> None:
    truth = dot_truth(*POSES[0])
    far = np.array([[5.0, 5.0]])
    assert not any(rows.start <= 5 < rows.stop and cols.start <= 5 < cols.stop for rows, cols in detector().windows)
    dots = detector().detect(draw_dots(np.vstack((truth.pixels, far))))
    assert dots.extra == 0 and dots.found.all()


def test_a_second_spot_on_a_beams_curve_loses_to_the_one_nearer_the_previous_dot() -> None:
    truth, elsewhere = dot_truth(*POSES[0]), dot_truth((0.0, 0.0, -2.2), (0.0, 0.0, 0.0))
    image = draw_dots(np.vstack((truth.pixels, elsewhere.pixels[:1])))  # beam 0's curve, another length
    previous = truth.pixels + [[1.5, -2.0], [0.5, 0.5], [np.nan, np.nan]]
    dots = detector().detect(image, previous)
    assert dots.extra == 1 and dots.found.all()
    assert np.abs(dots.pixels - truth.pixels).max() < 0.15
    previous[0] = elsewhere.pixels[0]  # the prior follows the other spot: it wins
    assert np.abs(detector().detect(image, previous).pixels[0] - elsewhere.pixels[0]).max() < 0.15


def test_with_the_previous_dots_only_squares_around_them_are_read_and_a_miss_falls_back_to_the_windows() -> None:
    truth = dot_truth(*POSES[0])
    stray = truth.pixels[:1] + [0.0, 40.0]  # in beam 0's search window, outside its 30 px tracking square
    image = draw_dots(np.vstack((truth.pixels, stray)))
    assert detector().detect(image).extra == 1
    tracked = detector().detect(image, truth.pixels + 2.0)  # the dots moved 2 px since the previous frame
    assert tracked.found.all() and tracked.extra == 0
    assert np.abs(tracked.pixels - truth.pixels).max() < 0.15
    lost = detector().detect(image, truth.pixels + [80.0, 0.0])  # a wrong previous: not all three nearby
    assert lost.found.all() and np.abs(lost.pixels - truth.pixels).max() < 0.15


def test_a_missing_dot_leaves_only_its_beam_unfound() -> None:
    truth = dot_truth(*POSES[1])
    dots = detector().detect(draw_dots(truth.pixels[[0, 2]]))
    assert dots.found.tolist() == [True, False, True] and dots.extra == 0
    assert np.isnan(dots.pixels[1]).all() and math.isnan(dots.lengths_m[1]) and math.isnan(dots.miss_m[1])
    assert np.abs(dots.pixels[[0, 2]] - truth.pixels[[0, 2]]).max() < 0.15


def test_a_floor_without_dots_gives_none_and_no_reason() -> None:
    dots = detector().detect(draw_dots(np.empty((0, 2))))
    assert not dots.found.any() and dots.extra == 0 and dots.reason is None


def test_a_saturated_image_gives_no_dots_and_says_why() -> None:
    grey = background()
    grey[:, :400] = 255.0  # overexposed: 62 % of the image white
    dots = detector().detect(draw_dots(dot_truth(*POSES[0]).pixels, grey))
    assert_no_dots(dots, SATURATED_REASON)
    grey[:, 200:400] = 120.0  # 31 %: still too much
    assert_no_dots(detector().detect(draw_dots(dot_truth(*POSES[0]).pixels, grey)), SATURATED_REASON)
    grey[:, 100:200] = 120.0  # 16 %: usable
    assert detector().detect(draw_dots(dot_truth(*POSES[0]).pixels, grey)).found.all()


def test_a_grey_image_gives_no_dots_and_says_the_camera_must_deliver_colour() -> None:
    image = cv2.cvtColor(draw_dots(dot_truth(*POSES[0]).pixels), cv2.COLOR_BGR2GRAY)
    assert_no_dots(detector().detect(image), GREY_REASON)


def assert_no_dots(dots: Dots, reason: str) -> None:
    assert dots.reason == reason and not dots.found.any() and np.isnan(dots.pixels).all()


# -- floor markers ------------------------------------------------------------------------------

FLOOR_MARKERS = (FloorMarker(7, (0.35, 0.3), 0.2, 15.0), FloorMarker(3, (-0.3, 0.4), 0.2, -80.0),
                 FloorMarker(11, (0.05, -0.45), 0.25, 170.0), FloorMarker(42, (-0.35, -0.2), 0.15, 60.0))
SIM_DISTORTION = (-0.12, 0.02, 0.001, -0.0005, 0.0)
VEHICLE = ((0.05, -0.02, -1.0), (3.0, -2.0, 20.0))  # ~1 m above the floor, slightly tilted


class FixedTruth:
    """TruthSource-like: one pose at all times."""

    def __init__(self, position: tuple[float, float, float], rpy_deg: tuple[float, float, float]) -> None:
        self.position_ned = np.array(position)
        self.quat = quat_from_euler(*np.radians(rpy_deg))

    def at(self, t: float) -> FixedTruth:
        return self


def sim_camera(markers: tuple[FloorMarker, ...]) -> SimulatedCamera:
    world = World(name="floor", wall_angle_deg=90, bounds=Bounds((-5.0, -5.0), (5.0, 5.0)), start=(0.0, 0.0, 0.0),
                  walls=(), floor_markers=markers)
    settings = SimCameraSettings(noise_sigma=0.0, distortion=SIM_DISTORTION)
    return SimulatedCamera("cam", settings, settings.intrinsics(), Mount.from_config(MountConfig(rpy_deg=(0, -90, 0))),
                           world, FixedTruth(*VEHICLE))


def rendered_view(markers: tuple[FloorMarker, ...],
                  known: tuple[FloorMarker, ...]) -> tuple[SimulatedCamera, FloorMapper, FloorView | None]:
    """The simulated camera over ``markers``, a floor mapper knowing ``known`` and its view of the frame."""
    cam = sim_camera(markers)
    mapper = FloorMapper(cam.calibration, known)
    return cam, mapper, mapper.find(cam.render(0.0, cam.truth.at(0.0)).image)


def floor_to_pixels(cam: SimulatedCamera, floor: np.ndarray) -> np.ndarray:
    """(N, 2) pixels where the simulated camera at the vehicle pose sees the (N, 2) floor points."""
    rotation, centre = cam.camera_pose(cam.truth.at(0.0))
    return cam.calibration.project((np.column_stack((floor, np.zeros(len(floor)))) - centre) @ rotation)


def pixels_to_floor(cam: SimulatedCamera, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) floor points on the rays of the (N, 2) pixels for the true camera pose."""
    rotation, centre = cam.camera_pose(cam.truth.at(0.0))
    rays = np.column_stack((cam.calibration.undistort_points(pixels), np.ones(len(pixels)))) @ rotation.T
    return (centre + (-centre[2] / rays[:, 2:]) * rays)[:, :2]


FLOOR_GRID = np.array([[n, e] for n in np.linspace(-0.4, 0.4, 5) for e in np.linspace(-0.45, 0.45, 5)])


def test_floor_points_seen_in_a_rendered_frame_map_back_within_5_mm() -> None:
    cam, mapper, view = rendered_view(FLOOR_MARKERS, FLOOR_MARKERS)
    assert view is not None and sorted(view.marker_ids) == [3, 7, 11, 42] and view.n_points == 16
    assert view.ignored == 0 and view.rms_m < 0.003
    floor, _ = mapper.to_floor(view, floor_to_pixels(cam, FLOOR_GRID))
    errors = np.linalg.norm(floor - FLOOR_GRID, axis=1)
    assert errors.max() < 0.005, errors
    cov = mapper.floor_covariance(view, floor_to_pixels(cam, FLOOR_GRID))
    sigma = np.sqrt(np.trace(cov, axis1=1, axis2=2))  # per point, both axes
    assert np.all((0.0001 < sigma) & (sigma < 0.003)) and np.sqrt(np.mean((errors / sigma) ** 2)) < 3


def test_a_point_far_outside_the_markers_maps_with_a_larger_covariance_than_one_among_them() -> None:
    one_side = FLOOR_MARKERS[:1]  # marker 7 alone, at north 0.35, east 0.3
    cam, mapper, view = rendered_view(one_side, one_side)
    assert view is not None
    pixels = floor_to_pixels(cam, np.array([[0.35, 0.3], [-0.4, -0.45]]))  # on the marker; 1 m away
    near, far = np.sqrt(np.trace(mapper.floor_covariance(view, pixels), axis1=1, axis2=2))
    assert far > 5 * near


def test_the_floor_jacobian_carries_a_pixel_step_like_the_true_geometry() -> None:
    cam, mapper, view = rendered_view(FLOOR_MARKERS, FLOOR_MARKERS)
    assert view is not None
    pixels = floor_to_pixels(cam, FLOOR_GRID)
    floor, jacobian = mapper.to_floor(view, np.vstack((pixels, [[np.nan, np.nan]])))
    assert np.isnan(floor[-1]).all() and np.isnan(jacobian[-1]).all()
    for axis in (0, 1):
        step = np.zeros(2)
        step[axis] = 1.0
        true = (pixels_to_floor(cam, pixels + step) - pixels_to_floor(cam, pixels - step)) / 2.0
        assert np.abs(jacobian[:-1, :, axis] - true).max() < 0.02 * np.abs(true).max()


def test_camera_pose_from_several_markers_matches_the_truth() -> None:
    cam, mapper, view = rendered_view(FLOOR_MARKERS, FLOOR_MARKERS)
    assert view is not None
    assert_pose_close(mapper.camera_pose(view), cam.camera_pose(cam.truth.at(0.0)))


def test_camera_pose_from_a_single_marker_matches_the_truth() -> None:
    marker = FloorMarker(5, (0.1, 0.05), 0.5, 35.0)  # 150 px wide; a 0.3 m one errs ~0.8 deg with 0.2 px corners
    cam, mapper, view = rendered_view((marker,), (marker,))
    assert view is not None and view.marker_ids == (5,) and view.rms_m < 1e-6  # 4 corners fit exactly
    truth = cam.camera_pose(cam.truth.at(0.0))
    assert_pose_close(mapper.camera_pose(view), truth)
    exact = cam.calibration.undistort_points(floor_to_pixels(cam, marker.corners()))
    rotation, centre = mapper.camera_pose(dataclasses.replace(view, corner_normalised=exact.reshape(1, 4, 2)))
    assert np.allclose(rotation, truth[0], atol=1e-7) and np.allclose(centre, truth[1], atol=1e-7)


def assert_pose_close(found: tuple[np.ndarray, np.ndarray] | None, truth: tuple[np.ndarray, np.ndarray]) -> None:
    assert found is not None
    angle = np.degrees(np.linalg.norm(cv2.Rodrigues(found[0].T @ truth[0])[0]))
    assert angle < 0.5 and np.linalg.norm(found[1] - truth[1]) < 0.01, (angle, found[1] - truth[1])


def test_markers_with_ids_outside_the_world_are_ignored_and_counted() -> None:
    _, _, view = rendered_view(FLOOR_MARKERS, FLOOR_MARKERS[:2])
    assert view is not None and sorted(view.marker_ids) == [3, 7] and view.ignored == 2
    assert rendered_view(FLOOR_MARKERS, (FloorMarker(99, (0.0, 0.0), 0.2),))[2] is None


def test_a_colour_frame_gives_the_same_floor_as_its_grey_version() -> None:
    cam, mapper, view = rendered_view(FLOOR_MARKERS, FLOOR_MARKERS)
    grey = cam.render(0.0, cam.truth.at(0.0)).image
    colour = mapper.find(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    assert view is not None and colour is not None
    assert np.allclose(colour.homography, view.homography) and colour.marker_ids == view.marker_ids


def test_tracked_markers_around_a_predicted_pose_are_the_whole_image_ones_at_a_fraction_of_the_search() -> None:
    cam, mapper, whole = rendered_view(FLOOR_MARKERS, FLOOR_MARKERS)
    image = cam.render(0.0, cam.truth.at(0.0)).image
    rotation, centre = cam.camera_pose(cam.truth.at(0.0))
    nudge = cv2.Rodrigues(np.radians([1.0, -0.5, 2.0]))[0]  # the previous frame's pose: 2.3 deg and 4 cm off
    predicted = (nudge @ rotation, centre + [0.03, -0.02, 0.02])
    boxes = mapper.predicted_boxes(*predicted)
    assert sorted(boxes) == [3, 7, 11, 42]
    assert sum((r.stop - r.start) * (c.stop - c.start) for r, c in boxes.values()) < 0.4 * image.size
    tracked = mapper.find(image, predicted)
    assert whole is not None and tracked is not None and sorted(tracked.marker_ids) == sorted(whole.marker_ids)
    order = [tracked.marker_ids.index(i) for i in whole.marker_ids]
    assert np.abs(tracked.corner_pixels[order] - whole.corner_pixels).max() < 0.05


def test_a_wrong_prediction_falls_back_to_searching_the_whole_image() -> None:
    cam, mapper, whole = rendered_view(FLOOR_MARKERS, FLOOR_MARKERS)
    rotation, centre = cam.camera_pose(cam.truth.at(0.0))
    far = (rotation, centre + [3.0, 0.0, 0.0])  # predicts the markers out of view
    tracked = mapper.find(cam.render(0.0, cam.truth.at(0.0)).image, far)
    assert whole is not None and tracked is not None and sorted(tracked.marker_ids) == sorted(whole.marker_ids)


def test_best_assignment_takes_most_beams_then_least_cost_as_an_exhaustive_search_would() -> None:
    def reference(cost: np.ndarray) -> tuple[int, ...]:  # the rule, spelled out over every choice
        best, best_key = (-1,) * cost.shape[0], (0, 0.0)
        for choice in itertools.product(range(-1, cost.shape[1]), repeat=cost.shape[0]):
            taken = [k for k in choice if k >= 0]
            costs = [cost[i, k] for i, k in enumerate(choice) if k >= 0]
            if len(set(taken)) == len(taken) and np.all(np.isfinite(costs)):
                key = (-len(costs), float(np.sum(costs)))
                if key < best_key:
                    best, best_key = choice, key
        return best

    rng = np.random.default_rng(4)
    for n in range(0, 6):
        for _ in range(40):
            cost = rng.uniform(0.0, 4.0, (3, n))
            cost[rng.uniform(size=cost.shape) < 0.4] = np.inf
            assert best_assignment(cost) == reference(cost), cost
