"""OpenCV cameras (``kind: camera, backend: real``), and what both camera backends share.

The backend (:class:`OpenCvCamera`) reads one of:

- a V4L2 camera: ``device`` an index (0 = /dev/video0) or a device path (/dev/video0,
  /dev/v4l/by-id/...), configured with ``width``, ``height``, ``fps``, ``fourcc`` and
  ``exposure_s`` (best effort: what the camera accepted is logged);
- a GStreamer pipeline ending in ``appsink`` (``gstreamer``), if this OpenCV has GStreamer
  (the pipeline sets size, rate and format);
- a video file (``device`` any other string: a path, relative to the config file's directory),
  played at its own frame rate (CAP_PROP_FPS), first frame at open, ending with EndOfData.

Timing: a live frame is stamped ``arrival - latency_s`` on the daemon clock (arrival = when
OpenCV's read returned; latency_s = mid-exposure to arrival, to be measured per camera); a
recording's frame ``open time + (t_i - t_0)`` and delivered at that time.

Threads: ``VideoCapture`` blocks (open: up to seconds; read: until the next frame), so each
open camera has a reader thread that opens, reads and releases it (OpenCV is never touched
from two threads) and hands frames to the event loop through a queue of :data:`QUEUE_FRAMES`.
A live camera keeps reading and drops the oldest frame when the queue is full (a slow consumer
sees the newest frames; the loss shows as a ``Frame.sequence`` gap and in ``overflowed``); a
recording waits for room, so nothing is lost. :class:`ThreadedCamera` (thread, queue, stamps,
pacing, calibration) and :class:`Recording` (recording times, looping) are shared with
drivers/camera_replay.py.

Errors: a device that is missing or that OpenCV cannot open raises OSError from ``open()``
(the frontend retries with backoff); a failed read or no frame for ``timeout_s`` raises
DeviceLost; a calibration file that does not load, or whose resolution the stream does not have
(a different aspect ratio: a scaled one is rescaled), is an OSError at open naming it.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import stat
import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.calibration import CameraCalibration, load_calibration
from companion.messages import Frame
from companion.plugins import register_backend
from companion.schema import meta
from drivers.base import Backend, CorruptFrame, DeviceLost, EndOfData

log = logging.getLogger("companion.drivers.camera")

QUEUE_FRAMES = 4  # between a reader thread and the loop (0.13 s at 30 fps)
JOIN_TIMEOUT_S = 2.0  # close() waits this long for a reader thread stuck in a driver call, then leaves it
V4L2_EXPOSURE_UNIT_S = 1e-4  # V4L2 exposure_time_absolute counts 100 us
V4L2_EXPOSURE_MANUAL, V4L2_EXPOSURE_AUTO = 1, 3  # V4L2 exposure_auto menu: manual, aperture priority

Item = tuple[float, int, np.ndarray]  # (time s, sequence, image) from FrameSource.read
TERMINAL = (OSError, EndOfData)  # a source that raised one of these is done


@dataclass(frozen=True)
class OpenCvCameraSettings:
    """``settings:`` of a camera with ``backend: real`` (a companion.schema dataclass)."""

    device: int | str | None = field(default=None, metadata=meta(
        "V4L2 camera: index (0 = /dev/video0) or device path (/dev/video0, /dev/v4l/by-id/...); any other "
        "string is a video file (relative to the config file's directory) played at its own frame rate. "
        "null with gstreamer."))
    gstreamer: str | None = field(default=None, metadata=meta(
        "GStreamer pipeline ending in appsink (needs an OpenCV built with GStreamer), instead of device."))
    width: int | None = field(default=None, metadata=meta(
        "Requested image width, pixels (V4L2 devices); null = the camera's default.", (1, 16384)))
    height: int | None = field(default=None, metadata=meta(
        "Requested image height, pixels (V4L2 devices); null = the camera's default.", (1, 16384)))
    fps: float | None = field(default=None, metadata=meta(
        "Requested frame rate, Hz (V4L2 devices); null = the camera's default.", (0.1, 1000)))
    fourcc: str | None = field(default=None, metadata=meta(
        "Requested pixel format, 4 characters such as MJPG or YUYV (V4L2 devices); null = the camera's default."))
    exposure_s: float | None = field(default=None, metadata=meta(
        "Fixed exposure time, seconds (V4L2 devices, best effort); null = automatic exposure.", (1e-5, 10)))
    latency_s: float = field(default=0.0, metadata=meta(
        "Mid-exposure to the frame's arrival, seconds: live frames are stamped arrival - latency_s.", (0, 1)))
    timeout_s: float = field(default=2.0, metadata=meta(
        "No frame for this long (the first one included): the camera is lost and reopened, seconds.", (0.1, 60)))
    calibration: str | None = field(default=None, metadata=meta(
        "Intrinsics: an OpenCV FileStorage or ROS camera_info YAML file, relative to the config file's "
        "directory; null = uncalibrated."))

    def validate(self) -> tuple[str, str] | None:
        if (self.device is None) == (self.gstreamer is None):
            return "device", "set either device or gstreamer"
        if self.fourcc is not None and (len(self.fourcc) != 4 or not self.fourcc.isascii()):
            return "fourcc", f"must be 4 ASCII characters (e.g. MJPG), got {self.fourcc!r}"
        return None


def is_live_device(device: int | str) -> bool:
    """An index or a /dev path: a camera (anything else names a video file)."""
    return isinstance(device, int) or device.startswith("/dev/")


def regular_file(path: Path) -> Path:
    """``path`` if it is a regular file; OSError otherwise (a FIFO is never opened)."""
    if not stat.S_ISREG(os.stat(path).st_mode):
        raise OSError(f"{path}: not a regular file")
    return path


# -- sources: blocking, used on a reader thread only --------------------------------------------------


class FrameSource(ABC):
    """A blocking source of images, opened, read and released on one reader thread."""

    description = "camera"
    live = True  # stamped at arrival; False: a recording, stamped by its recording times
    exposure_s: float | None = None  # the exposure time, s, once open, if known
    first_time = 0.0  # a recording's time of its first frame, s

    @abstractmethod
    def open(self) -> None:
        """Open the device or file; OSError if it is not there or cannot be decoded."""

    @abstractmethod
    def read(self) -> Item:
        """(time, sequence, image (H, W) or (H, W, 3) uint8 BGR): time = ``time.monotonic()`` at
        arrival for a live source, the frame's recording time (s) for a recording. Raises
        CorruptFrame (skip it), OSError (lost) or EndOfData."""

    def size(self) -> tuple[int, int] | None:
        """(width, height) of the images once open, pixels, if known."""
        return None

    @abstractmethod
    def release(self) -> None:
        """Close the device or file; never raises."""


class _CaptureOwner:
    """Size and release of the cv2.VideoCapture a source holds in ``_cap`` (None when closed)."""

    _cap: cv2.VideoCapture | None = None

    def size(self) -> tuple[int, int] | None:
        return _capture_size(self._cap)

    def release(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class LiveCapture(_CaptureOwner, FrameSource):
    """A V4L2 camera or a GStreamer pipeline, through cv2.VideoCapture."""

    def __init__(self, settings: OpenCvCameraSettings) -> None:
        self.settings = settings
        self.description = camera_description(settings)
        self._cap: cv2.VideoCapture | None = None
        self._sequence = 0

    def open(self) -> None:
        s = self.settings
        if s.gstreamer is not None:
            if not cv2.videoio_registry.hasBackend(cv2.CAP_GSTREAMER):
                raise OSError("this OpenCV is built without GStreamer (cv2.getBuildInformation()): "
                              "use device, or an OpenCV with GStreamer")
            cap = cv2.VideoCapture(s.gstreamer, cv2.CAP_GSTREAMER)
        else:
            assert s.device is not None
            path = f"/dev/video{s.device}" if isinstance(s.device, int) else s.device
            if not stat.S_ISCHR(os.stat(path).st_mode):  # FileNotFoundError when unplugged
                raise OSError(f"{path}: not a video device")
            cap = cv2.VideoCapture(os.path.realpath(path), cv2.CAP_V4L2)
        if not cap.isOpened():
            cap.release()
            raise OSError("OpenCV cannot open it (busy, or not a capture device?)")
        self._cap = cap
        if s.gstreamer is None:
            self._configure(cap)

    def _configure(self, cap: cv2.VideoCapture) -> None:
        """Ask for the configured format (fourcc first: it decides the sizes on offer), log what was granted."""
        s = self.settings
        if s.fourcc is not None:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*s.fourcc))
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, s.width), (cv2.CAP_PROP_FRAME_HEIGHT, s.height),
                            (cv2.CAP_PROP_FPS, s.fps)):
            if value is not None:
                cap.set(prop, value)
        if s.exposure_s is None:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_AUTO)
        elif cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, V4L2_EXPOSURE_MANUAL) and \
                cap.set(cv2.CAP_PROP_EXPOSURE, s.exposure_s / V4L2_EXPOSURE_UNIT_S):
            self.exposure_s = cap.get(cv2.CAP_PROP_EXPOSURE) * V4L2_EXPOSURE_UNIT_S
        else:
            log.warning("%s: a fixed exposure of %g s was refused; exposure stays as the camera has it",
                        self.description, s.exposure_s)
        code = int(cap.get(cv2.CAP_PROP_FOURCC))
        fourcc = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4)) if code > 0 else "?"
        width, height = self.size() or (0, 0)
        log.info("%s: %dx%d %s at %g fps, exposure %s", self.description, width, height, fourcc,
                 cap.get(cv2.CAP_PROP_FPS), "auto" if self.exposure_s is None else f"{self.exposure_s:g} s")

    def read(self) -> Item:
        assert self._cap is not None
        ok, image = self._cap.read()
        arrival = time.monotonic()
        if not ok or image is None:
            raise DeviceLost("the camera delivered no frame (unplugged?)")
        self._sequence += 1
        return arrival, self._sequence - 1, image



def camera_description(settings: OpenCvCameraSettings) -> str:
    if settings.gstreamer is not None:
        return "GStreamer camera pipeline"
    return f"camera {settings.device}"


def _capture_size(cap: cv2.VideoCapture | None) -> tuple[int, int] | None:
    if cap is None:
        return None
    size = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    return size if min(size) > 0 else None


class Recording(FrameSource):
    """The frames of a file or folder with their recording times: ``timestamps`` (s, increasing,
    one per frame; playing stops when either runs out) or frame i at i / ``fps``. With ``loop``
    it plays again and again, each pass one frame period (median interval) after the previous
    pass's last frame, sequence numbers going on. Subclasses deliver the images."""

    live = False

    def __init__(self, timestamps: np.ndarray | None, fps: float | None, loop: bool) -> None:
        self.timestamps = timestamps
        self.fps = fps  # a subclass may learn it at open (a video file's own rate)
        self.loop = loop
        self._index = 0  # next frame of this pass
        self._good = 0  # frames delivered on this pass
        self._pass_time = 0.0  # added to this pass's recording times, s
        self._pass_sequence = 0  # sequence number of this pass's first frame
        if timestamps is not None:
            self.first_time = float(timestamps[0])

    @abstractmethod
    def _image(self, index: int) -> np.ndarray | None:
        """Image ``index`` of the pass (called in order), None after the last; CorruptFrame if unreadable."""

    def _rewind(self) -> None:
        """Get ready to deliver image 0 again."""

    def _time(self, index: int) -> float:
        if self.timestamps is not None:
            return float(self.timestamps[index])
        assert self.fps is not None
        return index / self.fps

    def _period(self) -> float:
        if self.timestamps is not None and len(self.timestamps) > 1:
            return float(np.median(np.diff(self.timestamps)))
        return 1.0 / self.fps if self.fps else 0.1

    def read(self) -> Item:
        while True:
            i = self._index
            self._index += 1
            image = self._image(i) if self.timestamps is None or i < len(self.timestamps) else None
            if image is not None:
                self._good += 1
                return self._pass_time + self._time(i), self._pass_sequence + i, image
            if not self.loop or self._good == 0:
                raise EndOfData(f"{self.description}: all {self._pass_sequence + i} frames played")
            self._pass_time += self._time(i - 1) + self._period() - self._time(0)
            self._pass_sequence += i
            self._index = self._good = 0
            self._rewind()


class VideoFile(_CaptureOwner, Recording):
    """A video file OpenCV decodes (FFmpeg), at ``fps`` or its own frame rate unless timed by ``timestamps``."""

    def __init__(self, path: Path, timestamps: np.ndarray | None = None, fps: float | None = None,
                 loop: bool = False) -> None:
        super().__init__(timestamps, fps, loop)
        self.path = path
        self.description = f"video {path.name}"
        self._cap: cv2.VideoCapture | None = None

    def open(self) -> None:
        self._cap = cv2.VideoCapture(str(regular_file(self.path)), cv2.CAP_ANY)
        if not self._cap.isOpened():
            self.release()
            raise OSError(f"{self.path}: OpenCV cannot decode this video")
        if self.timestamps is None and self.fps is None:
            rate = self._cap.get(cv2.CAP_PROP_FPS)
            if not (math.isfinite(rate) and rate > 0):
                self.release()
                raise OSError(f"{self.path}: the video has no frame rate: give fps or timestamps")
            self.fps = rate

    def _image(self, index: int) -> np.ndarray | None:
        assert self._cap is not None
        ok, image = self._cap.read()
        return image if ok else None

    def _rewind(self) -> None:
        self.release()
        self.open()



# -- the reader thread and the backend around it ----------------------------------------------------


class _Reader:
    """One opened source on its own thread, handing items (or the exception a read raised) to the
    event loop through a queue of QUEUE_FRAMES. Made per open: a thread that outlives its close
    can only touch its own queue."""

    def __init__(self, source: FrameSource, name: str) -> None:
        self.source = source
        self.loop = asyncio.get_running_loop()
        self.items: deque[Item | Exception] = deque()
        self.overflowed = 0  # live frames dropped because the queue was full
        self.arrived = asyncio.Event()
        self.opened: asyncio.Future[None] = self.loop.create_future()
        self.stop = threading.Event()
        self.room = threading.Semaphore(QUEUE_FRAMES)  # a recording's reads wait for room
        self.thread = threading.Thread(target=self._run, name=f"camera {name}", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self.source.open()
        except OSError as exc:
            self._post(self._settle, exc)
            return
        except Exception as exc:  # e.g. cv2.error on a pipeline it cannot parse: as absent, retried
            log.exception("%s: open failed", self.source.description)
            self._post(self._settle, OSError(f"open failed: {exc!r}"))
            return
        try:
            if not self._post(self._settle, None):
                return
            while not self.stop.is_set():
                if not self.source.live and not self.room.acquire(timeout=0.1):
                    continue
                try:
                    item: Item | Exception = self.source.read()
                except (CorruptFrame, *TERMINAL) as exc:
                    item = exc
                except Exception as exc:  # an OpenCV failure: lost, reopened, not a dead thread
                    log.exception("%s: read failed", self.source.description)
                    item = DeviceLost(f"read failed: {exc!r}")
                if not self._post(self._put, item) or isinstance(item, TERMINAL):
                    return
        finally:
            self.source.release()

    def _post(self, callback: Any, arg: object) -> bool:
        """Run ``callback(arg)`` on the loop; False if the loop is gone."""
        try:
            self.loop.call_soon_threadsafe(callback, arg)
        except RuntimeError:
            return False
        return True

    def _settle(self, exc: OSError | None) -> None:
        if self.opened.done():  # open() was cancelled
            self.stop.set()
        elif exc is None:
            self.opened.set_result(None)
        else:
            self.opened.set_exception(exc)

    def _put(self, item: Item | Exception) -> None:
        if self.source.live and not isinstance(item, Exception):
            t, sequence, image = item
            item = (t + self.loop.time() - time.monotonic(), sequence, image)  # arrival on the daemon clock
            if len(self.items) >= QUEUE_FRAMES:
                self.items.popleft()
                self.overflowed += 1
        self.items.append(item)
        self.arrived.set()

    async def get(self, timeout_s: float | None) -> Item:
        """The next item; raises what the source raised (a terminal exception on every later call too)."""
        while not self.items:
            self.arrived.clear()
            try:
                await asyncio.wait_for(self.arrived.wait(), timeout_s)
            except TimeoutError:
                raise DeviceLost(f"no frame for {timeout_s:g} s") from None
        item = self.items[0]
        if isinstance(item, TERMINAL):
            raise item
        self.items.popleft()
        if not self.source.live:
            self.room.release()
        if isinstance(item, Exception):
            raise item
        return item

    async def close(self) -> None:
        self.stop.set()
        self.room.release()
        if self.thread.is_alive():
            await asyncio.to_thread(self.thread.join, JOIN_TIMEOUT_S)
        if self.thread.is_alive():
            log.warning("%s: the reader thread is still in a driver call; it releases the device when that returns",
                        self.source.description)


class ThreadedCamera(Backend[Frame]):
    """A camera backend over a :class:`FrameSource` read on its own thread (see the module docstring).

    ``calibration`` is None, or after ``open()`` the intrinsics for the stream's resolution.
    Subclasses say what to read (:meth:`make_source`, called at every open).
    """

    def __init__(self, camera_id: str, calibration_file: Path | None, latency_s: float = 0.0,
                 timeout_s: float | None = None) -> None:
        self.camera_id = camera_id
        self.calibration_file = calibration_file
        self.latency_s = latency_s  # live frames: mid-exposure to arrival, s
        self.timeout_s = timeout_s  # live frames: none for this long = lost, s
        self.calibration: CameraCalibration | None = None
        self.overflowed = 0  # live frames dropped by past sessions (the current one: _reader.overflowed)
        self._reader: _Reader | None = None
        self._offset = 0.0  # a recording's daemon time of recording time 0, s

    @abstractmethod
    def make_source(self) -> FrameSource:
        """A new, unopened source (OSError if the settings name something unreadable)."""

    async def open(self) -> None:
        """Load the calibration, open the source on a new reader thread; a recording starts now."""
        calibration = self._load_calibration()
        reader = _Reader(self.make_source(), self.camera_id)
        self._reader = reader
        try:
            await reader.opened
            self.calibration = self._fit(calibration, reader.source.size())
        except BaseException:
            reader.stop.set()
            self._reader = None
            raise
        self._offset = reader.loop.time() - reader.source.first_time

    def _load_calibration(self) -> CameraCalibration | None:
        if self.calibration_file is None:
            return None
        try:
            return load_calibration(self.calibration_file)
        except ValueError as exc:
            raise OSError(f"calibration: {exc}") from exc

    def _fit(self, calibration: CameraCalibration | None, size: tuple[int, int] | None) -> CameraCalibration | None:
        """``calibration`` for images of ``size`` (rescaled if it is another resolution of the same aspect)."""
        if calibration is None or size is None or size == (calibration.width, calibration.height):
            return calibration
        try:
            scaled = calibration.scaled(*size)
        except ValueError as exc:
            raise OSError(f"calibration {self.calibration_file}: the stream is {size[0]}x{size[1]}: {exc}") from exc
        log.info("%s: calibration %s rescaled from %dx%d to %dx%d", self.description, self.calibration_file,
                 calibration.width, calibration.height, *size)
        return scaled

    async def read(self) -> Frame:
        """The next frame: a live one as soon as it is read, a recording's at its replay time."""
        reader = self._reader
        if reader is None:
            raise DeviceLost("not open")
        live = reader.source.live
        t, sequence, image = await reader.get(self.timeout_s if live else None)
        if live:
            t_capture = t - self.latency_s
        else:
            t_capture = self._offset + t
            await asyncio.sleep(max(0.0, t_capture - reader.loop.time()))
        image.flags.writeable = False  # every subscriber gets this one array
        try:
            return Frame(self.camera_id, t_capture, image, sequence, reader.source.exposure_s)
        except ValueError as exc:
            raise CorruptFrame(f"frame {sequence}: {exc}") from None

    async def close(self) -> None:
        """Stop the reader thread (it releases the source)."""
        reader, self._reader = self._reader, None
        if reader is not None:
            self.overflowed += reader.overflowed
            await reader.close()


class OpenCvCamera(ThreadedCamera):
    """``kind: camera, backend: real``: a V4L2 camera, a GStreamer pipeline or a video file."""

    def __init__(self, camera_id: str, settings: OpenCvCameraSettings, base_dir: Path = Path(".")) -> None:
        calibration = None if settings.calibration is None else base_dir / settings.calibration
        super().__init__(camera_id, calibration, settings.latency_s, settings.timeout_s)
        self.settings = settings
        self.base_dir = base_dir
        self.description = camera_description(settings)

    def make_source(self) -> FrameSource:
        device = self.settings.device
        if device is not None and not is_live_device(device):
            return VideoFile(self.base_dir / device)
        return LiveCapture(self.settings)


def check_calibration(cfg: Any, name: str) -> None:
    """check-config: the calibration file ``sensors.<name>.settings.calibration`` names, if any, loads."""
    value = cfg.sensors[name].settings.get("calibration")
    if value is not None:
        cfg.load_referenced(f"sensors.{name}.settings.calibration", value, load_calibration)


def _check_files(cfg: Any, name: str) -> None:
    """check-config: the calibration loads; a video file given as ``device`` is a regular file."""
    device = cfg.sensors[name].settings.get("device")
    if isinstance(device, str) and not is_live_device(device):
        cfg.load_referenced(f"sensors.{name}.settings.device", device, regular_file)
    check_calibration(cfg, name)


@register_backend("camera", "real", OpenCvCameraSettings, check_files=_check_files)
def _opencv_camera(name: str, settings: OpenCvCameraSettings, ctx: Any) -> OpenCvCamera:
    """A V4L2 camera, a GStreamer pipeline or a video file (paced at its frame rate), through OpenCV's VideoCapture."""
    return OpenCvCamera(name, settings, base_dir=ctx.base_dir)
