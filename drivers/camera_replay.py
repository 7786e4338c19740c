"""Replay of recorded images as a camera backend (``kind: camera, backend: replay``).

A recording is a video file (any format this OpenCV decodes) or a folder of .png / .jpg images
played in name order (sort the names: zero-padded numbers). Frame times come from a timestamps
file, else from ``fps``, else (a video) from the file's own frame rate. The timestamps file is
text: one capture time in seconds per frame, in the first comma-separated column (so a
``time,name`` CSV works), increasing; blank lines, ``#`` comments and one header line are skipped.
An image folder needs as many times as images; a video plays until its frames or its times run out.

Timing, as drivers/lidar_replay.py: frame i is stamped ``open time + (t_i - t_0)`` on the daemon
clock and delivered at that time; with ``loop`` the recording starts over one median frame
interval after its last frame, sequence numbers going on (``Frame.sequence`` is the frame's
index in the recording plus the recording's length per pass before, so a skipped frame leaves a
gap). An image that cannot be read or decoded raises :class:`~drivers.base.CorruptFrame` (the
frontend counts and skips it); the end raises :class:`~drivers.base.EndOfData`. Reading and
pacing are drivers/camera_opencv.py's (:class:`~drivers.camera_opencv.ThreadedCamera`,
:class:`~drivers.camera_opencv.Recording`): decoding runs on a reader thread, a few frames ahead.
"""

from __future__ import annotations

import math
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.plugins import register_backend
from companion.schema import meta, read_regular_file
from drivers.base import CorruptFrame
from drivers.camera_opencv import FrameSource, Recording, ThreadedCamera, VideoFile, check_calibration

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
IMAGE_MAX_BYTES = 64 << 20  # one image file (a 4K PNG is ~25 MB)
TIMESTAMPS_MAX_BYTES = 16 << 20  # ~1 M frames


@dataclass(frozen=True)
class ReplayCameraSettings:
    """``settings:`` of a camera with ``backend: replay`` (a companion.schema dataclass)."""

    path: str = field(metadata=meta(
        "A video file, or a folder of .png/.jpg images played in name order; relative to the config "
        "file's directory."))
    timestamps: str | None = field(default=None, metadata=meta(
        "Text file of capture times, seconds, one per frame (first CSV column); null = a fixed frame rate."))
    fps: float | None = field(default=None, metadata=meta(
        "Frame rate without timestamps, Hz; null = the video's own (an image folder needs fps or timestamps).",
        (0.01, 1000)))
    loop: bool = field(default=False, metadata=meta("Start over at the end instead of ending."))
    calibration: str | None = field(default=None, metadata=meta(
        "Intrinsics: an OpenCV FileStorage or ROS camera_info YAML file, relative to the config file's "
        "directory; null = uncalibrated."))


def read_timestamps(path: str | Path) -> np.ndarray:
    """The capture times (s, (N,) float64, strictly increasing, N >= 1) in the text file at ``path``
    (see the module docstring); OSError if it cannot be read, ValueError naming its line otherwise."""
    text = read_regular_file(path, TIMESTAMPS_MAX_BYTES).decode("utf-8", errors="replace")
    times: list[float] = []
    header_allowed = True
    for number, line in enumerate(text.splitlines(), start=1):
        cell = line.split(",", 1)[0].strip()
        if not cell or cell.startswith("#"):
            continue
        try:
            t = float(cell)
        except ValueError:
            if header_allowed:
                header_allowed = False
                continue
            raise ValueError(f"{path}:{number}: not a time in seconds: {cell[:40]!r}") from None
        header_allowed = False
        if not math.isfinite(t):
            raise ValueError(f"{path}:{number}: time {cell!r} is not finite")
        if times and t <= times[-1]:
            raise ValueError(f"{path}:{number}: time {t!r} s is not after the previous one ({times[-1]!r} s)")
        times.append(t)
    if not times:
        raise ValueError(f"{path}: no times in the file")
    return np.array(times)


def image_files(folder: Path) -> list[Path]:
    """The .png / .jpg / .jpeg files directly in ``folder``, sorted by name; OSError if there are none."""
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise OSError(f"{folder}: no {', '.join(IMAGE_SUFFIXES)} images in the folder")
    return files


def decode_image(path: Path) -> np.ndarray:
    """The image in the file at ``path``: (H, W) uint8 grey or (H, W, 3) uint8 BGR (alpha dropped,
    16-bit scaled to 8); CorruptFrame if it cannot be read or decoded."""
    try:
        data = read_regular_file(path, IMAGE_MAX_BYTES)
    except OSError as exc:
        raise CorruptFrame(f"{path.name}: cannot read: {exc.strerror or exc}") from None
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_ANYCOLOR)
    if image is None:
        raise CorruptFrame(f"{path.name}: not a PNG or JPEG image OpenCV can decode")
    return image


class ImageFolder(Recording):
    """The images of a folder in name order, timed by ``timestamps`` (one per image) or ``fps``."""

    def __init__(self, folder: Path, timestamps: np.ndarray | None, fps: float | None, loop: bool) -> None:
        super().__init__(timestamps, fps, loop)
        self.folder = folder
        self.description = f"images in {folder.name}"
        self._files: list[Path] = []
        self._size: tuple[int, int] | None = None

    def open(self) -> None:
        self._files = image_files(self.folder)
        if self.timestamps is None and self.fps is None:
            raise OSError(f"{self.folder}: an image folder needs fps or timestamps")
        if self.timestamps is not None and len(self.timestamps) != len(self._files):
            raise OSError(f"{self.folder}: {len(self._files)} images but {len(self.timestamps)} timestamps")
        try:
            height, width = decode_image(self._files[0]).shape[:2]
            self._size = (width, height)
        except CorruptFrame:
            self._size = None  # read() reports it; the size is checked on none

    def _image(self, index: int) -> np.ndarray | None:
        return decode_image(self._files[index]) if index < len(self._files) else None

    def size(self) -> tuple[int, int] | None:
        return self._size

    def release(self) -> None:
        self._files = []


class ReplayCamera(ThreadedCamera):
    """A recorded video or image folder played on the daemon clock (see the module docstring);
    paths are resolved against ``base_dir`` (the config file's directory)."""

    def __init__(self, camera_id: str, settings: ReplayCameraSettings, base_dir: Path = Path(".")) -> None:
        calibration = None if settings.calibration is None else base_dir / settings.calibration
        super().__init__(camera_id, calibration)
        self.settings = settings
        self.path = base_dir / settings.path
        self.timestamps_file = None if settings.timestamps is None else base_dir / settings.timestamps
        self.description = f"replay of {self.path.name}"

    def make_source(self) -> FrameSource:
        """The recording, its timestamps read (OSError if they cannot be, or are malformed)."""
        timestamps = None
        if self.timestamps_file is not None:
            try:
                timestamps = read_timestamps(self.timestamps_file)
            except ValueError as exc:
                raise OSError(str(exc)) from exc
        s = self.settings
        if stat.S_ISDIR(os.stat(self.path).st_mode):
            return ImageFolder(self.path, timestamps, s.fps, s.loop)
        return VideoFile(self.path, timestamps, s.fps, s.loop)


def _check_files(cfg: Any, name: str) -> None:
    """check-config: the recording is there, its timestamps and calibration load."""
    settings = cfg.sensors[name].settings
    key = f"sensors.{name}.settings"
    cfg.load_referenced(f"{key}.path", settings["path"], os.stat)
    if settings.get("timestamps") is not None:
        cfg.load_referenced(f"{key}.timestamps", settings["timestamps"], read_timestamps)
    check_calibration(cfg, name)


@register_backend("camera", "replay", ReplayCameraSettings, check_files=_check_files)
def _replay_camera(name: str, settings: ReplayCameraSettings, ctx: Any) -> ReplayCamera:
    """A recorded video or image folder played on the daemon clock at its timestamps or frame rate."""
    return ReplayCamera(name, settings, base_dir=ctx.base_dir)
