"""Camera backends (drivers/camera_opencv.py, drivers/camera_replay.py) and calibration files
(companion/calibration.py), with real OpenCV on videos, images and calibrations written here."""

from __future__ import annotations

import asyncio
import logging
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from companion.calibration import CameraCalibration, load_calibration
from companion.health import Health, State
from companion.messages import Frame
from companion.schema import SchemaError, load_text
from drivers.base import Backend, DeviceLost, EndOfData, SensorDriver
from drivers.camera_opencv import FrameSource, OpenCvCamera, OpenCvCameraSettings, ThreadedCamera
from drivers.camera_replay import ReplayCamera, ReplayCameraSettings, read_timestamps
from drivers.checks import KINDS
from tests.conftest import REPO

SIZE = (64, 48)  # width, height of the test images, pixels
K = np.array([[500.0, 0.0, 319.5], [0.0, 505.0, 239.5], [0.0, 0.0, 1.0]])
D_PLUMB_BOB = np.array([-0.28, 0.07, 0.001, -0.0005, 0.01])
D_EQUIDISTANT = np.array([0.05, -0.01, 0.003, -0.001])


def numbered_image(number: int, grey: bool = False) -> np.ndarray:
    """A flat image whose level encodes ``number`` (flat areas survive JPEG to about 2 levels)."""
    shape = (SIZE[1], SIZE[0]) if grey else (SIZE[1], SIZE[0], 3)
    return np.full(shape, 10 + 20 * number, dtype=np.uint8)


def number_of(image: np.ndarray) -> int:
    return round((float(image.mean()) - 10) / 20)


def write_video(path: Path, count: int, fps: float) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, SIZE)
    assert writer.isOpened()
    for i in range(count):
        writer.write(numbered_image(i))
    writer.release()


async def drive(backend: Backend[Frame], until: Callable[[SensorDriver, Health], bool], limit_s: float = 10.0,
                ) -> tuple[SensorDriver, list[Frame], list[float], float]:
    """Run ``backend`` under the real frontend with the camera kind's check until ``until``; returns the
    driver, the frames its subscriber got, when each arrived and when the run started (daemon clock, s)."""
    loop = asyncio.get_running_loop()
    health = Health(loop.time)
    kind = KINDS["camera"]
    driver = SensorDriver("cam", backend, health, kind.check, kind.stamp)
    frames: list[Frame] = []
    delivered: list[float] = []
    driver.subscribe(lambda f: (frames.append(f), delivered.append(loop.time())))
    started = loop.time()
    task = asyncio.create_task(driver.run())
    while not until(driver, health) and loop.time() < started + limit_s:
        assert not task.done(), task
        await asyncio.sleep(0.01)
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    return driver, frames, delivered, started


def finished(driver: SensorDriver, health: Health) -> bool:
    h = health.get("sensor:cam")
    return h is not None and h.reason == "replay finished"


def reader_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name == "camera cam"]


# -- the OpenCV backend ------------------------------------------------------------------------------


def test_a_video_file_plays_at_its_frame_rate_with_its_content(tmp_path: Path) -> None:
    write_video(tmp_path / "clip.avi", 12, fps=25.0)
    backend = OpenCvCamera("cam", OpenCvCameraSettings(device="clip.avi"), base_dir=tmp_path)
    driver, frames, delivered, started = asyncio.run(drive(backend, finished))
    assert driver.stats.messages == 12 and driver.stats.corrupt_frames == 0
    assert [number_of(f.image) for f in frames] == list(range(12))
    assert [f.sequence for f in frames] == list(range(12))
    assert all(f.image.shape == (48, 64, 3) and f.camera_id == "cam" for f in frames)
    stamps = np.array([f.t_capture for f in frames])
    np.testing.assert_allclose(np.diff(stamps), 1 / 25.0, atol=1e-9)
    assert stamps[0] == pytest.approx(started, abs=0.2)
    lateness = np.array(delivered) - stamps
    assert (lateness >= -1e-6).all() and (lateness < 0.05).all()  # paced on the daemon clock, not all at once


def test_a_missing_device_or_file_is_retried_with_backoff_not_a_crash(tmp_path: Path,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG, logger="companion.drivers")
    for device, why in (("/dev/video99", "No such file"), ("missing.avi", "No such file")):
        caplog.clear()
        backend = OpenCvCamera("cam", OpenCvCameraSettings(device=device), base_dir=tmp_path)
        health_seen: list[Health] = []

        def three_attempts(driver: SensorDriver, health: Health) -> bool:
            health_seen[:] = [health]
            return sum("cam: cannot open" in r.getMessage() for r in caplog.records) >= 3

        driver, frames, _, _ = asyncio.run(drive(backend, three_attempts, limit_s=3.0))
        assert sum("cam: cannot open" in r.getMessage() for r in caplog.records) >= 3  # 0, 0.25, 0.75 s
        h = health_seen[0].get("sensor:cam")
        assert h is not None and h.state == State.LOST and device in h.reason and why in h.reason
        assert frames == [] and driver.stats.last_error == h.reason


class TickingCamera(FrameSource):
    """A live source: a numbered frame every 10 ms, ``count`` of them, then none for 0.5 s."""

    description = "ticking camera"

    def __init__(self, count: int) -> None:
        self.count = count
        self.arrivals: list[float] = []  # time.monotonic() of each frame
        self.released = threading.Event()

    def open(self) -> None:
        pass

    def read(self) -> tuple[float, int, np.ndarray]:
        n = len(self.arrivals)
        if n == self.count:
            time.sleep(0.5)
            raise DeviceLost("stopped")
        time.sleep(0.01)
        self.arrivals.append(time.monotonic())
        return self.arrivals[-1], n, numbered_image(n)

    def release(self) -> None:
        self.released.set()


class Ticking(ThreadedCamera):
    def __init__(self, source: TickingCamera) -> None:
        super().__init__("cam", None, latency_s=0.005, timeout_s=0.2)
        self.source = source

    def make_source(self) -> FrameSource:
        return self.source


def test_a_live_camera_keeps_the_newest_frames_stamped_at_arrival_and_is_lost_when_silent() -> None:
    source = TickingCamera(10)
    backend = Ticking(source)

    async def run() -> list[Frame]:
        await backend.open()
        while len(source.arrivals) < 10:  # nobody reads meanwhile: the queue keeps the newest
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.02)
        frames = [await backend.read() for _ in range(4)]
        with pytest.raises(DeviceLost, match="no frame for 0.2 s"):
            await backend.read()
        await backend.close()
        return frames

    frames = asyncio.run(run())
    assert [f.sequence for f in frames] == [6, 7, 8, 9] and backend.overflowed == 6
    assert [number_of(f.image) for f in frames] == [6, 7, 8, 9]
    np.testing.assert_allclose([f.t_capture for f in frames], np.array(source.arrivals[6:]) - 0.005, atol=1e-3)
    assert source.released.is_set() and reader_threads() == []


@pytest.mark.skipif(cv2.videoio_registry.hasBackend(cv2.CAP_GSTREAMER), reason="this OpenCV has GStreamer")
def test_a_gstreamer_pipeline_without_gstreamer_is_a_clear_error_at_open() -> None:
    backend = OpenCvCamera("cam", OpenCvCameraSettings(gstreamer="videotestsrc ! videoconvert ! appsink"))
    with pytest.raises(OSError, match="built without GStreamer"):
        asyncio.run(backend.open())


def test_the_example_camera_settings_type_check_and_bad_ones_are_named() -> None:
    example = yaml.safe_load((REPO / "config" / "example-ardupilot-hokuyo.yaml").read_text())
    settings = load_text(yaml.safe_dump(example["sensors"]["camera_down"]["settings"]), OpenCvCameraSettings)
    assert (settings.device, settings.width, settings.height, settings.fps) == ("/dev/video0", 640, 480, 30.0)
    assert load_text("device: 2", OpenCvCameraSettings).device == 2
    for text, message in (("{}", "device: set either device or gstreamer"),
                          ("{device: 0, gstreamer: 'x ! appsink'}", "device: set either device or gstreamer"),
                          ("{device: 0, fourcc: MJPEG}", "fourcc: must be 4 ASCII characters")):
        with pytest.raises(SchemaError, match=message):
            load_text(text, OpenCvCameraSettings)


# -- the replay backend ------------------------------------------------------------------------------


def test_an_image_folder_replays_at_its_timestamps_skipping_a_corrupt_image(tmp_path: Path) -> None:
    folder = tmp_path / "images"
    folder.mkdir()
    for i in range(6):
        cv2.imwrite(str(folder / f"{i:03d}.{'png' if i % 2 else 'jpg'}"), numbered_image(i, grey=True))
    (folder / "003.png").write_bytes(b"not an image")
    (folder / "notes.txt").write_text("not a frame")
    times = [1000.0, 1000.04, 1000.1, 1000.12, 1000.2, 1000.26]
    (tmp_path / "times.csv").write_text("time_s,file\n# written by the test\n"
                                        + "".join(f"{t},{i:03d}\n" for i, t in enumerate(times)))
    backend = ReplayCamera("cam", ReplayCameraSettings(path="images", timestamps="times.csv"), base_dir=tmp_path)
    driver, frames, delivered, started = asyncio.run(drive(backend, finished))
    assert driver.stats.messages == 5 and driver.stats.corrupt_frames == 1
    assert "003.png" in (driver.stats.last_error or "")
    assert [f.sequence for f in frames] == [0, 1, 2, 4, 5]  # the corrupt image is a gap
    assert [number_of(f.image) for f in frames] == [0, 1, 2, 4, 5]
    assert all(f.image.shape == (48, 64) for f in frames)  # grey stays grey
    stamps = np.array([f.t_capture for f in frames])
    np.testing.assert_allclose(stamps - stamps[0], np.array(times)[[0, 1, 2, 4, 5]] - times[0], atol=1e-9)
    assert stamps[0] == pytest.approx(started, abs=0.2)
    assert all(0 <= d - s < 0.05 for d, s in zip(delivered, stamps))


def test_a_replay_ends_or_loops_on_at_its_frame_rate(tmp_path: Path) -> None:
    write_video(tmp_path / "clip.avi", 3, fps=10.0)

    async def run(loop: bool, count: int) -> list[Frame]:
        backend = ReplayCamera("cam", ReplayCameraSettings(path="clip.avi", fps=100.0, loop=loop), base_dir=tmp_path)
        await backend.open()
        try:
            frames = [await backend.read() for _ in range(count)]
            if not loop:
                with pytest.raises(EndOfData):
                    await backend.read()
        finally:
            await backend.close()
        return frames

    assert [number_of(f.image) for f in asyncio.run(run(False, 3))] == [0, 1, 2]
    assert reader_threads() == []  # closing ended the reader thread
    looped = asyncio.run(run(True, 7))
    assert [f.sequence for f in looped] == list(range(7))
    assert [number_of(f.image) for f in looped] == [0, 1, 2, 0, 1, 2, 0]
    np.testing.assert_allclose(np.diff([f.t_capture for f in looped]), 0.01, atol=1e-9)  # fps overrides the file's


def test_timestamps_that_do_not_increase_name_their_line(tmp_path: Path) -> None:
    path = tmp_path / "times.csv"
    path.write_text("0.0\n0.1\n0.1\n")
    with pytest.raises(ValueError, match=r"times.csv:3: time 0.1 s is not after the previous one"):
        read_timestamps(path)
    path.write_text("time\n0.0\nabc\n")
    with pytest.raises(ValueError, match=r"times.csv:3: not a time in seconds"):
        read_timestamps(path)


# -- calibration files -------------------------------------------------------------------------------


def write_filestorage(path: Path, D: np.ndarray, model: str) -> None:
    """As OpenCV 5 writes it (header %YAML 1.2)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", D.reshape(1, -1))
    if model == "equidistant":
        fs.write("distortion_model", model)
    fs.release()


def write_opencv4_yaml(path: Path, D: np.ndarray, model: str) -> None:
    """As OpenCV 4's calibration sample writes it (header %YAML:1.0, fisheye_model flag)."""
    def matrix(m: np.ndarray) -> str:
        return (f"!!opencv-matrix\n   rows: {m.shape[0]}\n   cols: {m.shape[1]}\n   dt: d\n"
                f"   data: [ {', '.join(repr(float(v)) for v in m.ravel())} ]\n")
    path.write_text(f"%YAML:1.0\n---\ncalibration_time: \"Mon 01 Jan\"\nimage_width: 640\nimage_height: 480\n"
                    f"fisheye_model: {int(model == 'equidistant')}\ncamera_matrix: {matrix(K)}"
                    f"distortion_coefficients: {matrix(D.reshape(-1, 1))}avg_reprojection_error: 0.21\n")


def write_ros_yaml(path: Path, D: np.ndarray, model: str) -> None:
    """As ROS's camera_calibration_parsers writes it."""
    path.write_text(yaml.safe_dump({
        "image_width": 640, "image_height": 480, "camera_name": "down",
        "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
        "distortion_model": model,
        "distortion_coefficients": {"rows": 1, "cols": len(D), "data": D.tolist()},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": np.eye(3).ravel().tolist()},
        "projection_matrix": {"rows": 3, "cols": 4, "data": np.hstack([K, np.zeros((3, 1))]).ravel().tolist()},
    }, sort_keys=False))


@pytest.mark.parametrize("model, D", [("plumb_bob", D_PLUMB_BOB), ("equidistant", D_EQUIDISTANT)])
def test_one_calibration_in_every_format_loads_to_the_same_intrinsics(tmp_path: Path, model: str,
                                                                       D: np.ndarray) -> None:
    loaded = []
    for write in (write_filestorage, write_opencv4_yaml, write_ros_yaml):
        path = tmp_path / f"{write.__name__}.yaml"
        write(path, D, model)
        loaded.append(load_calibration(path))
    for calibration in loaded:
        assert (calibration.width, calibration.height, calibration.model) == (640, 480, model)
        np.testing.assert_array_equal(calibration.K, K)
        np.testing.assert_array_equal(calibration.D, D)


ROS_GOOD = ("image_width: 640\nimage_height: 480\ncamera_matrix: {rows: 3, cols: 3, data: [500, 0, 320, 0, 500, "
            "240, 0, 0, 1]}\ndistortion_model: plumb_bob\ndistortion_coefficients: {rows: 1, cols: 5, "
            "data: [0.1, 0, 0, 0, 0]}\n")


@pytest.mark.parametrize("text, message", [
    (ROS_GOOD.replace("camera_matrix", "camera_matrx"), r":3: camera_matrx: unknown key"),
    (ROS_GOOD.replace("image_height: 480\n", ""), r":1: image_height: required key is missing"),
    (ROS_GOOD.replace("0, 0, 1]", "0, 1]"), r":3: camera_matrix.data: 8 values for a 3x3 matrix"),
    (ROS_GOOD.replace("[500,", "[-500,"), r":3: camera_matrix: must be \[\[fx, 0, cx\]"),
    (ROS_GOOD.replace("320, 0", "900, 0"), r":3: camera_matrix: principal point \(900, 240\) is outside"),
    (ROS_GOOD.replace("plumb_bob", "equidistant"), r":5: distortion_coefficients: equidistant takes 4"),
    (ROS_GOOD.replace("plumb_bob", "kannala_brandt"), r":4: distortion_model: must be one of"),
    (ROS_GOOD.replace("image_width: 640", "image_width: wide"), r":1: image_width: expected an integer"),
    ("%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n"
     "  dt: d\n  data: [500, 0, 320, 0, 500, 240, 0, 0, 1]\n", r": distortion_coefficients: required key is missing"),
    ("%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [1, 2\n",
     r": not an OpenCV FileStorage file: .*Parsing error"),
    ("just words", r":1: expected a mapping of keys"),
    ("\xff\xfe", r": not a calibration file: not UTF-8"),
])
def test_a_bad_calibration_file_is_a_value_error_naming_the_file_and_key(tmp_path: Path, text: str,
                                                                          message: str) -> None:
    path = tmp_path / "cal.yaml"
    path.write_bytes(text.encode("latin-1"))
    with pytest.raises(ValueError, match=f"^{path}{message}"):
        load_calibration(path)


def test_a_calibration_that_is_not_a_regular_file_is_an_os_error(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "fifo")
    for path in (tmp_path, tmp_path / "fifo", tmp_path / "missing.yaml"):
        with pytest.raises(OSError):
            load_calibration(path)


@pytest.mark.parametrize("model, D", [("plumb_bob", D_PLUMB_BOB), ("equidistant", D_EQUIDISTANT)])
def test_undistort_points_inverts_project_within_a_thousandth_of_a_pixel(model: str, D: np.ndarray) -> None:
    calibration = CameraCalibration(640, 480, K, D, model)  # type: ignore[arg-type]
    x, y = np.meshgrid(np.linspace(-0.55, 0.55, 12), np.linspace(-0.4, 0.4, 9))  # the whole image, corners too
    points = np.column_stack([x.ravel(), y.ravel(), np.ones(x.size)]) * 2.5  # metres, camera frame
    pixels = calibration.project(points)
    assert ((pixels >= 0) & (pixels <= [639, 479])).all()
    ideal = points[:, :2] / points[:, 2:]
    error_px = (calibration.undistort_points(pixels) - ideal) * [K[0, 0], K[1, 1]]
    assert np.abs(error_px).max() < 1e-3
    ideal_px = ideal * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.abs(calibration.undistort_points(pixels, to_pixels=True) - ideal_px).max() < 1e-3
    assert np.isnan(calibration.project(np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]))).all()  # behind: no pixel


def test_undistort_maps_are_made_once_and_show_where_each_ray_lands() -> None:
    calibration = CameraCalibration(640, 480, K, D_PLUMB_BOB)
    map_x, map_y = calibration.undistort_maps()
    assert map_x.shape == (480, 640) and calibration.undistort_maps()[0] is map_x
    for u, v in ((0, 0), (100, 400), (320, 240), (639, 479)):
        ray = np.linalg.solve(K, [u, v, 1.0])
        np.testing.assert_allclose([map_x[v, u], map_y[v, u]], calibration.project(ray[None])[0], atol=1e-2)


def test_a_calibration_for_another_resolution_is_rescaled_or_refused(tmp_path: Path) -> None:
    full = CameraCalibration(128, 96, [[100.0, 0, 63.5], [0, 100.0, 47.5], [0, 0, 1]], D_PLUMB_BOB)
    half = full.scaled(64, 48)
    point = np.array([[0.1, -0.2, 1.0]])
    np.testing.assert_allclose(half.project(point), (full.project(point) + 0.5) / 2 - 0.5, atol=1e-9)
    with pytest.raises(ValueError, match="different aspect ratio"):
        full.scaled(64, 64)

    folder = tmp_path / "images"
    folder.mkdir()
    cv2.imwrite(str(folder / "0.png"), numbered_image(0))
    for size, fits in (((128, 96), True), ((100, 100), False)):
        write_ros_yaml(tmp_path / "cal.yaml", D_PLUMB_BOB, "plumb_bob")
        text = (tmp_path / "cal.yaml").read_text()
        (tmp_path / "cal.yaml").write_text(text.replace("640", str(size[0])).replace("480", str(size[1]))
                                           .replace("319.5", "50.0").replace("239.5", "40.0"))
        backend = ReplayCamera("cam", ReplayCameraSettings(path="images", fps=10.0, calibration="cal.yaml"),
                               base_dir=tmp_path)

        async def open_and_close() -> None:
            try:
                await backend.open()
            finally:
                await backend.close()

        if fits:
            asyncio.run(open_and_close())
            assert backend.calibration is not None and (backend.calibration.width, backend.calibration.height) == SIZE
        else:
            with pytest.raises(OSError, match="the stream is 64x48: calibrated at 100x100"):
                asyncio.run(open_and_close())
