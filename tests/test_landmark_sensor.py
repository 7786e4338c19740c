"""The simulated landmark sensor (the EKF-SLAM seed's vision sensor), the landmarks kind's
frontend check and the world's landmarks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from companion.frames import quat_from_euler
from companion.messages import LandmarkSightings
from companion.schema import SchemaError
from companion.world import Landmark, load_world
from drivers.checks import landmarks_problem
from drivers.mount import Mount
from sitl.landmark_sensor import SimLandmarkSettings, SimulatedLandmarkSensor
from sitl.truth import TruthSample

NADIR = Mount(np.eye(3), np.zeros(3))  # sensor +z = body down


def sample(position: tuple[float, float, float], rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> TruthSample:
    return TruthSample(0.0, np.array(position, dtype=float), np.zeros(3), quat_from_euler(*np.radians(rpy_deg)))


def sensor(landmarks: list[Landmark], **settings: float) -> SimulatedLandmarkSensor:
    return SimulatedLandmarkSensor("cam", SimLandmarkSettings(**settings), NADIR, tuple(landmarks), truth=None)


def exact(**settings: float) -> dict[str, float]:
    return {"range_sigma_m": 0.0, "azimuth_sigma_deg": 0.0, "elevation_sigma_deg": 0.0, **settings}


def test_a_landmark_below_and_ahead_right_gives_its_range_azimuth_from_the_heading_and_negative_elevation() -> None:
    # Vehicle 100 m up heading east (yaw 90 deg); the landmark 10 m south-east of below it.
    s = sensor([Landmark(7, (-10.0, 10.0), 0.0)], **exact())
    frame = s.sightings(1.0, sample((0.0, 0.0, -100.0), (0.0, 0.0, 90.0)))
    assert list(frame.ids) == [7]
    assert frame.range_m[0] == pytest.approx(math.sqrt(100 ** 2 + 200))
    assert frame.azimuth_rad[0] == pytest.approx(math.radians(45.0))  # south-east is 45 deg right of east
    assert frame.elevation_rad[0] == pytest.approx(-math.atan2(100.0, math.sqrt(200)))


def test_only_landmarks_inside_the_cone_around_the_tilted_boresight_are_seen() -> None:
    half = 100.0 * math.tan(math.radians(20.0))  # 36.4 m footprint radius at 100 m
    landmarks = [Landmark(1, (half - 1.0, 0.0)), Landmark(2, (half + 1.0, 0.0)), Landmark(3, (-half + 1.0, 0.0))]
    level = sensor(landmarks, **exact()).visible(sample((0.0, 0.0, -100.0)))[0]
    assert sorted(level) == [1, 3]
    # Heading north, pitched 5 deg nose up: the belly, and the boresight, swing forward (north).
    pitched = sensor(landmarks, **exact()).visible(sample((0.0, 0.0, -100.0), (0.0, 5.0, 0.0)))[0]
    assert sorted(pitched) == [1, 2]


def test_a_landmark_nearer_than_the_minimum_range_is_not_seen() -> None:
    pad = [Landmark(640, (0.0, 0.0), 0.0)]
    assert list(sensor(pad).visible(sample((0.0, 0.0, 0.0)))[0]) == []  # on the ground over the pad
    assert list(sensor(pad).visible(sample((0.0, 0.0, -1.5)))[0]) == [640]
    assert list(sensor(pad, min_range_m=2.0).visible(sample((0.0, 0.0, -1.5)))[0]) == []


def test_the_noise_has_the_stated_sigmas() -> None:
    s = sensor([Landmark(1, (5.0, 3.0), 2.0)])
    truth = sensor([Landmark(1, (5.0, 3.0), 2.0)], **exact()).sightings(0.0, sample((0.0, 0.0, -100.0)))
    frames = [s.sightings(0.0, sample((0.0, 0.0, -100.0))) for _ in range(4000)]
    errors = np.array([[f.range_m[0] - truth.range_m[0], f.azimuth_rad[0] - truth.azimuth_rad[0],
                        f.elevation_rad[0] - truth.elevation_rad[0]] for f in frames])
    assert np.allclose(errors.std(axis=0), frames[0].sigma, rtol=0.06)
    assert frames[0].sigma == pytest.approx((0.2, math.radians(0.16), math.radians(0.12)))


def test_a_roll_error_of_the_levelling_attitude_shifts_the_bearings_and_a_yaw_error_does_not() -> None:
    s = sensor([Landmark(1, (10.0, 0.0))], **exact(attitude_error_deg=1.0))
    s._attitude_error = np.radians([0.0, 0.0, 3.0])  # heading error only: azimuth is relative to the heading
    clean = sensor([Landmark(1, (10.0, 0.0))], **exact()).sightings(0.0, sample((0.0, 0.0, -100.0)))
    yawed = s.sightings(0.0, sample((0.0, 0.0, -100.0)))
    assert yawed.azimuth_rad[0] == pytest.approx(clean.azimuth_rad[0], abs=1e-12)
    s._attitude_error = np.radians([0.0, 1.0, 0.0])
    pitched = s.sightings(0.0, sample((0.0, 0.0, -100.0)))
    assert abs(pitched.elevation_rad[0] - clean.elevation_rad[0]) == pytest.approx(math.radians(1.0), abs=1e-4)


def test_the_frontend_refuses_a_nan_bearing_a_zero_range_and_a_repeated_id() -> None:
    def frame(ids: list[int], ranges: list[float], azimuths: list[float]) -> LandmarkSightings:
        return LandmarkSightings("cam", 1.0, np.array(ids), np.array(ranges), np.array(azimuths),
                                 np.zeros(len(ids)), (0.2, 0.003, 0.002))
    assert landmarks_problem(frame([1, 2], [100.0, 101.0], [0.1, 0.2]), 0.5) is None
    assert landmarks_problem(frame([1], [100.0], [math.nan]), 0.5) is not None
    assert landmarks_problem(frame([1], [0.0], [0.1]), 0.5) is not None
    assert landmarks_problem(frame([1, 1], [100.0, 100.0], [0.1, 0.1]), 0.5) is not None
    assert landmarks_problem(frame([], [], []), 1.0) == "capture time not after the previous one's"


OUTDOOR = """\
name: field
wall_angle_deg: 90
bounds: {min: [-50, -50], max: [400, 400]}
start: [0, 0, 0]
base: [353.5, 353.5]
landmarks:
  - {id: 1, position: [10, 20], height_m: 3}
  - {id: 2, position: [30, 40]}
"""


def test_an_outdoor_world_needs_no_walls_and_its_landmarks_are_checked(tmp_path: Path) -> None:
    path = tmp_path / "field.yaml"
    path.write_text(OUTDOOR)
    world = load_world(path)
    assert world.base == (353.5, 353.5) and np.allclose(world.landmarks[0].ned(), [10.0, 20.0, -3.0])
    path.write_text(OUTDOOR.replace("{id: 2,", "{id: 1,"))
    with pytest.raises(SchemaError, match=r"landmarks\[1\].id.*used twice"):
        load_world(path)
    path.write_text(OUTDOOR.replace("[30, 40]", "[30, 900]"))
    with pytest.raises(SchemaError, match=r"landmarks\[1\].position"):
        load_world(path)
