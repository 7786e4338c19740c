"""Camera intrinsics: the pinhole matrix and distortion of one camera, and the files they come in.

Frame (OpenCV's optical frame): x right, y down in the image, z forward along the optical axis;
pixels (u, v) = (column, row), integer values at pixel centres. ``K`` maps normalised image
coordinates (x/z, y/z) to pixels; ``D`` is OpenCV's distortion vector for ``model``
("plumb_bob" = radial-tangential k1 k2 p1 p2 [k3 [k4 k5 k6 [s1..s4 [tx ty]]]], ROS's
"rational_polynomial" being its 8-coefficient form; "equidistant" = fisheye k1..k4).

:func:`load_calibration` reads both formats, auto-detected (../shared/REFERENCE.md "Camera
calibration files"):

- OpenCV FileStorage YAML (``%YAML:1.0`` or ``%YAML 1.2`` header, ``!!opencv-matrix`` nodes), as
  OpenCV's calibration sample writes it: ``image_width``, ``image_height``, ``camera_matrix``
  (3x3), ``distortion_coefficients``; the model is plumb_bob unless ``distortion_model`` says
  ``equidistant`` or ``fisheye_model`` is non-zero;
- ROS camera_info YAML (camera_calibration_parsers): ``image_width``, ``image_height``,
  ``camera_name``, ``camera_matrix: {rows, cols, data}``, ``distortion_model``,
  ``distortion_coefficients: {rows, cols, data}``, ``rectification_matrix``,
  ``projection_matrix`` (the last two are accepted and not used: a single camera's are I and K).

A file that is not one of these raises ValueError naming the file and the key (and, for ROS
YAML, the line); one that cannot be read raises OSError.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from companion.schema import SchemaError, meta, parse_document, read_regular_file

CALIBRATION_MAX_BYTES = 4 << 20  # OpenCV's sample also writes every view's points: ~100 kB
DISTORTION_LENGTHS = {"plumb_bob": (0, 4, 5, 8, 12, 14), "equidistant": (4,)}
ROS_MODELS: dict[str, Literal["plumb_bob", "equidistant"]] = {
    "plumb_bob": "plumb_bob", "rational_polynomial": "plumb_bob", "equidistant": "equidistant"}
# undistort_points iterates until the step is below 1e-12 (normalised units), at most 100 times
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
FILE_KEYS = {"width": "image_width", "height": "image_height", "K": "camera_matrix",
             "D": "distortion_coefficients", "model": "distortion_model"}  # attribute -> key in both formats


@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Intrinsics of one camera at one resolution (read-only arrays; ValueError if inconsistent)."""

    width: int  # pixels
    height: int
    K: np.ndarray  # (3, 3) pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], pixels
    D: np.ndarray  # (N,) distortion coefficients of ``model`` (an empty plumb_bob D is stored as 5 zeros)
    model: Literal["plumb_bob", "equidistant"] = "plumb_bob"

    def __post_init__(self) -> None:
        K = np.array(self.K, dtype=np.float64)
        D = np.array(self.D, dtype=np.float64).ravel()
        if D.size == 0 and self.model == "plumb_bob":
            D = np.zeros(5)
        problem = _problem(self.width, self.height, K, D, self.model)
        if problem is not None:
            raise ValueError(f"{problem[0]}: {problem[1]}")
        K.flags.writeable = D.flags.writeable = False
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "D", D)

    @functools.cached_property
    def _maps(self) -> tuple[np.ndarray, np.ndarray]:
        size = (self.width, self.height)
        if self.model == "equidistant":
            map_x, map_y = cv2.fisheye.initUndistortRectifyMap(self.K, self.D, np.eye(3), self.K, size, cv2.CV_32FC1)
        else:
            map_x, map_y = cv2.initUndistortRectifyMap(self.K, self.D, np.eye(3), self.K, size, cv2.CV_32FC1)
        map_x.flags.writeable = map_y.flags.writeable = False
        return map_x, map_y

    def undistort_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(map_x, map_y), float32 (height, width): pixel (u, v) of the undistorted image (same K,
        same size) shows the camera's pixel (map_x[v, u], map_y[v, u]); for
        ``cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR)``. Computed on the first call, then shared."""
        return self._maps

    def undistort_points(self, pixels: np.ndarray, to_pixels: bool = False) -> np.ndarray:
        """The (N, 2) camera pixels (u, v) with the lens distortion removed: normalised image
        coordinates (x/z, y/z) of their rays in the camera frame, or with ``to_pixels`` the pixels
        where an ideal pinhole camera with the same K would see them. The inverse of :meth:`project`
        (iterative; converged far below 1e-3 px within the image)."""
        src = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
        if len(src) == 0:
            return np.empty((0, 2))
        P = self.K if to_pixels else None
        if self.model == "equidistant":
            out = cv2.fisheye.undistortPoints(src, self.K, self.D, R=None, P=P, criteria=UNDISTORT_CRITERIA)
        elif hasattr(cv2, "undistortPointsIter"):  # OpenCV 4 names the variant with criteria so
            out = cv2.undistortPointsIter(src, self.K, self.D, None, P, UNDISTORT_CRITERIA)
        else:
            out = cv2.undistortPoints(src, self.K, self.D, R=None, P=P, criteria=UNDISTORT_CRITERIA)
        return out.reshape(-1, 2)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixels (u, v), (N, 2), where the camera sees the (N, 3) points given in its frame
        (metres or any unit: only directions matter), distortion included; NaN for points with
        z <= 0 (behind the camera). Points outside the field of view get pixels outside the image
        (or, far outside, wherever the distortion polynomial folds them)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.full((len(pts), 2), np.nan)
        front = pts[:, 2] > 0
        if front.any():
            obj = pts[front].reshape(-1, 1, 3)
            zero = np.zeros(3)
            if self.model == "equidistant":
                img, _ = cv2.fisheye.projectPoints(obj, zero, zero, self.K, self.D)
            else:
                img, _ = cv2.projectPoints(obj, zero, zero, self.K, self.D)
            out[front] = img.reshape(-1, 2)
        return out

    def scaled(self, width: int, height: int) -> CameraCalibration:
        """This calibration for the same sensor read out at ``width`` x ``height`` (binned or
        resized, same field of view); ValueError if the aspect ratio differs (a crop, not a scale)."""
        sx, sy = width / self.width, height / self.height
        if abs(sx - sy) > 1e-3 * max(sx, sy):
            raise ValueError(f"calibrated at {self.width}x{self.height}: {width}x{height} is a different aspect "
                             f"ratio (a crop), not a scaled image")
        K = self.K.copy()
        K[0, 0] *= sx
        K[1, 1] *= sy
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5  # pixel centres at integers: the image edge is at -0.5
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return CameraCalibration(width, height, K, self.D, self.model)


def _problem(width: int, height: int, K: np.ndarray, D: np.ndarray, model: str) -> tuple[str, str] | None:
    """(attribute, what is wrong) of the first inconsistent value, or None."""
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 0 < value <= 100_000:
            return name, f"must be a whole number of pixels in [1, 100000], got {value!r}"
    if model not in DISTORTION_LENGTHS:
        return "model", f"must be one of {', '.join(DISTORTION_LENGTHS)}, got {model!r}"
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        return "K", f"must be a 3x3 matrix of finite numbers, got shape {K.shape}"
    if not (K[0, 0] > 0 and K[1, 1] > 0) or not np.allclose([K[0, 1], K[1, 0], *K[2]], [0, 0, 0, 0, 1], atol=1e-12):
        return "K", f"must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, got {K.tolist()}"
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        return "K", f"principal point ({K[0, 2]:g}, {K[1, 2]:g}) is outside the {width}x{height} image"
    if D.size not in DISTORTION_LENGTHS[model] or not np.all(np.isfinite(D)):
        lengths = " or ".join(map(str, DISTORTION_LENGTHS[model]))
        return "D", f"{model} takes {lengths} finite coefficients, got {D.size}: {D.tolist()}"
    return None


def load_calibration(path: str | Path) -> CameraCalibration:
    """The calibration in the file at ``path`` (OpenCV FileStorage or ROS camera_info YAML, told
    apart by OpenCV's ``%YAML:`` header or ``!!opencv-matrix`` tags). OSError if the file is not a
    regular file of at most :data:`CALIBRATION_MAX_BYTES`; ValueError naming the file and the key."""
    file = str(path)
    data = read_regular_file(path, CALIBRATION_MAX_BYTES)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"{file}: not a calibration file: not UTF-8 text (byte {exc.start})") from None
    if text.startswith("%YAML:") or "!!opencv-matrix" in text:
        return _from_opencv(text, file)
    return _from_ros(text, file)


def _build(file: str, where: dict[str, str], width: object, height: object, K: np.ndarray, D: np.ndarray,
           model: str) -> CameraCalibration:
    """The calibration from the values read; ValueError at ``where[key]`` (``file:line`` or ``file``)."""
    problem = _problem(width, height, K, D, model)  # type: ignore[arg-type]
    if problem is not None:
        key = FILE_KEYS[problem[0]]
        raise ValueError(f"{where.get(key, file)}: {key}: {problem[1]}")
    return CameraCalibration(width, height, K, D, model)  # type: ignore[arg-type]


# -- OpenCV FileStorage ----------------------------------------------------------------------------


def _from_opencv(text: str, file: str) -> CameraCalibration:
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except (cv2.error, SystemError) as exc:  # the binding wraps a parse error in a SystemError
        raise ValueError(f"{file}: not an OpenCV FileStorage file: {_cv_message(exc)}") from None
    try:
        width = _fs_int(fs, "image_width", file)
        height = _fs_int(fs, "image_height", file)
        K = _fs_matrix(fs, "camera_matrix", file)
        D = _fs_matrix(fs, "distortion_coefficients", file)
        model_node = fs.getNode("distortion_model")
        if not model_node.empty():
            if not model_node.isString() or model_node.string() not in ROS_MODELS:
                raise ValueError(f"{file}: distortion_model: must be one of {', '.join(ROS_MODELS)}")
            model = ROS_MODELS[model_node.string()]
        else:
            fisheye = fs.getNode("fisheye_model")
            model = "equidistant" if not fisheye.empty() and fisheye.isInt() and fisheye.real() != 0 else "plumb_bob"
    finally:
        fs.release()
    return _build(file, {}, width, height, K, D.ravel(), model)


def _fs_node(fs: cv2.FileStorage, key: str, file: str) -> cv2.FileNode:
    node = fs.getNode(key)
    if node.empty():
        raise ValueError(f"{file}: {key}: required key is missing")
    return node


def _fs_int(fs: cv2.FileStorage, key: str, file: str) -> int:
    node = _fs_node(fs, key, file)
    if not node.isInt():
        raise ValueError(f"{file}: {key}: expected a whole number of pixels")
    return int(node.real())


def _fs_matrix(fs: cv2.FileStorage, key: str, file: str) -> np.ndarray:
    node = _fs_node(fs, key, file)
    try:
        mat = node.mat() if node.isMap() else None
    except cv2.error as exc:
        raise ValueError(f"{file}: {key}: not a valid !!opencv-matrix: {_cv_message(exc)}") from None
    if mat is None:
        raise ValueError(f"{file}: {key}: expected an !!opencv-matrix")
    return np.asarray(mat, dtype=np.float64)


def _cv_message(exc: BaseException) -> str:
    """The gist of an OpenCV error: the text after "error: " of it or of its cause."""
    if not isinstance(exc, cv2.error) and isinstance(exc.__cause__, cv2.error):
        exc = exc.__cause__
    text = str(exc).strip()
    return text.split("error: ", 1)[-1]


# -- ROS camera_info YAML -----------------------------------------------------------------------------


@dataclass
class _RosMatrix:
    rows: int = field(metadata=meta("Rows.", (1, 16)))
    cols: int = field(metadata=meta("Columns.", (0, 16)))
    data: list[float] = field(metadata=meta("rows x cols values, row by row."))

    def validate(self) -> tuple[str, str] | None:
        if len(self.data) != self.rows * self.cols:
            return "data", f"{len(self.data)} values for a {self.rows}x{self.cols} matrix"
        return None


@dataclass
class _RosCameraInfo:
    image_width: int
    image_height: int
    camera_matrix: _RosMatrix
    distortion_coefficients: _RosMatrix
    distortion_model: Literal["plumb_bob", "rational_polynomial", "equidistant"] = "plumb_bob"
    camera_name: str | None = None
    rectification_matrix: _RosMatrix | None = None
    projection_matrix: _RosMatrix | None = None


def _from_ros(text: str, file: str) -> CameraCalibration:
    try:
        document = parse_document(text, file)
        info = document.build(_RosCameraInfo)
    except SchemaError as exc:
        raise ValueError(str(exc)) from None
    where = {key: f"{file}:{document.line_of(key)}" for key in FILE_KEYS.values()}
    m = info.camera_matrix
    return _build(file, where, info.image_width, info.image_height, np.reshape(m.data, (m.rows, m.cols)),
                  np.asarray(info.distortion_coefficients.data), ROS_MODELS[info.distortion_model])
