"""``companion laser-dots calibrate``: the laser beams' origins and directions from a recording.

How to record: hold or fly the vehicle over the floor markers of the config's world, from low to
high (heights spanning at least 0.3 m; 0.4-1.8 m is better), turning and tilting a little, and
record the downward camera: a folder of .png / .jpg images (name order) or a video file.

What happens (companion/nav/laser_dots/): for every frame where the three dots and at least
``MIN_MARKERS`` floor markers are seen, the camera pose from the markers alone (solvePnP on
their corners) gives the body pose through the camera's mount (``sensors.<camera>.mount``), and
the homography puts each dot on the floor; each dot in the body frame then lies on its beam, and
:func:`~companion.nav.laser_dots.calibrate.calibrate_beams` fits the three lines. Which beam made
which dot comes from the nominal rig in the config (``pipelines.laser_dots.beams``): each dot is
given to the beam whose image curve is nearest, within ``CURVE_DISTANCE_PX``, so the nominal rig
must be within a few degrees of the truth. The result is the ``beams:`` section to put in the config.

The poses come from the markers, so their errors (a few tenths of a degree with one marker,
hundredths with several) set the calibration's: frames with more markers in view are better,
and many frames average the rest.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from companion.calibration import load_calibration
from companion.config import Config
from companion.nav.laser_dots.calibrate import BeamCalibration, Observation, calibrate_beams
from companion.nav.laser_dots.detect import DotDetector, DotParams
from companion.nav.laser_dots.floor import FloorMapper
from companion.nav.laser_dots.pipeline import LaserDotsConfig
from companion.world import load_world
from drivers.base import CorruptFrame, EndOfData
from drivers.camera_opencv import VideoFile
from drivers.camera_replay import ImageFolder
from drivers.mount import OPTICAL_TO_SENSOR, Mount

MIN_MARKERS = 2  # markers in view for a frame's pose to count (one marker's pose tilts by tenths of a degree)
# A dot may lie this far from its nominal beam's image curve (px): the beams are what is unknown here
# (2 degrees off moves a dot ~10 px at 1 m height with the 135-degree lens); in flight the gate is 4 px.
CURVE_DISTANCE_PX = 40.0
SECTION = "pipelines.laser_dots"


@dataclass(frozen=True)
class RecordingCalibration:
    """The calibration and how many frames of the recording served."""

    calibration: BeamCalibration
    frames: int  # frames read
    used: int  # frames with three dots and MIN_MARKERS markers


def recording_frames(source: Path) -> Iterator[np.ndarray]:
    """The images of a folder (name order) or a video file; unreadable frames are skipped."""
    recording = ImageFolder(source, None, 1.0, False) if source.is_dir() else VideoFile(source, None, 1.0)
    recording.open()
    try:
        while True:
            try:
                yield recording.read()[2]
            except CorruptFrame:
                continue
            except EndOfData:
                return
    finally:
        recording.release()


def calibrate_recording(cfg: Config, source: Path) -> RecordingCalibration:
    """Calibrate the beams of ``cfg``'s laser_dots pipeline from the recording at ``source``.
    ValueError (with what is missing) when the frames cannot determine the beams."""
    section = cfg.pipelines.enabled.get("laser_dots")
    if not isinstance(section, LaserDotsConfig):
        raise ValueError(f"the config has no {SECTION} section")
    calibration = cfg.load_referenced(f"{SECTION}.calibration", section.calibration, load_calibration)
    world = cfg.load_referenced(f"{SECTION}.world", section.world, load_world)
    mount = Mount.from_config(cfg.sensors[section.camera].mount)
    optical_to_body = mount.rotation @ OPTICAL_TO_SENSOR
    nominal = section.beams.rig()
    detector = DotDetector(calibration, optical_to_body, mount.offset_m, nominal,
                           DotParams(max_curve_distance_px=CURVE_DISTANCE_PX))
    mapper = FloorMapper(calibration, world.floor_markers)
    observations: list[Observation] = []
    frames = 0
    for image in recording_frames(source):
        frames += 1
        observation = _observe(image, detector, mapper, optical_to_body, mount.offset_m)
        if observation is not None:
            observations.append(observation)
    if not observations:
        raise ValueError(f"{source}: none of its {frames} frames shows the three dots and {MIN_MARKERS} markers")
    return RecordingCalibration(calibrate_beams(observations, nominal), frames, len(observations))


def _observe(image: np.ndarray, detector: DotDetector, mapper: FloorMapper, optical_to_body: np.ndarray,
             camera_origin_body: np.ndarray) -> Observation | None:
    """(rotation body -> NED, body origin NED m, (3, 2) floor dots m) of one frame, or None."""
    dots = detector.detect(image)
    if dots.reason is not None or not dots.found.all():
        return None
    view = mapper.find(image)
    if view is None or len(view.marker_ids) < MIN_MARKERS:
        return None
    camera = mapper.camera_pose(view)
    if camera is None:
        return None
    optical_to_ned, centre = camera
    body_to_ned = optical_to_ned @ optical_to_body.T
    floor, _ = mapper.to_floor(view, dots.pixels)
    return body_to_ned, centre - body_to_ned @ camera_origin_body, floor
