"""What the flight recorder writes: each typed message (companion/messages.py) as one JSON
document with a JSON Schema, exact both ways, and readable by Foxglove with no plug-in.

Exactness: a message decoded from its document equals the one encoded, bit for bit (floats are
written with Python's shortest round-trip repr; a non-finite float as the string ``"nan"``,
``"inf"`` or ``"-inf"``; a numpy array as ``{"dtype", "shape", "base64"}``, its raw bytes; a camera
image as lossless PNG). This is what makes ``companion replay`` deterministic. A scan's ranges are
Foxglove's ``ranges`` (valid beams exact, the others 0) with the others' values beside them.

Foxglove: the four message kinds Foxglove has a well-known schema for are written as that schema
(its fields, its name: ``foxglove.LaserScan``, ``foxglove.CompressedImage``,
``foxglove.LocationFix``, ``foxglove.PoseInFrame``) with the exact fields added beside them (JSON
Schema allows extra properties, Foxglove ignores them). The rest are ``companion.<Type>`` schemas
generated from the dataclasses. Foxglove's ``timestamp`` is the daemon's monotonic clock (s since
its boot, not the Unix epoch), the time base of every stamp in the recording.
"""

from __future__ import annotations

import base64
import dataclasses
import functools
import json
import math
import types
import typing
from typing import Any

import cv2
import numpy as np

from companion import messages
from companion.frames import quat_from_euler

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}
FRAME_ID_WORLD = "local_ned"  # MAVLink LOCAL_NED at the autopilot's EKF origin

# -- JSON Schema building blocks ------------------------------------------------------------

NUMBER: dict[str, Any] = {"anyOf": [{"type": "number"}, {"enum": list(NON_FINITE)}]}
ARRAY: dict[str, Any] = {
    "type": "object", "required": ["dtype", "shape", "base64"], "additionalProperties": False,
    "properties": {"dtype": {"type": "string", "description": "numpy dtype string, byte order included (e.g. <f8)"},
                   "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}},
                   "base64": {"type": "string", "contentEncoding": "base64", "description": "the C-order bytes"}}}
TIME: dict[str, Any] = {
    "type": "object", "required": ["sec", "nsec"],
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}
_XYZ = {"type": "object", "required": ["x", "y", "z"], "properties": {k: {"type": "number"} for k in "xyz"}}
_XYZW = {"type": "object", "required": ["x", "y", "z", "w"], "properties": {k: {"type": "number"} for k in "xyzw"}}
POSE: dict[str, Any] = {"type": "object", "required": ["position", "orientation"],
                        "properties": {"position": _XYZ, "orientation": _XYZW}}
# The fields of Foxglove's well-known schemas we fill (https://docs.foxglove.dev/docs/visualization/message-schemas)
FOXGLOVE_FIELDS: dict[str, dict[str, Any]] = {
    "foxglove.LaserScan": {
        "timestamp": TIME, "frame_id": {"type": "string"}, "pose": POSE, "start_angle": {"type": "number"},
        "end_angle": {"type": "number"}, "ranges": {"type": "array", "items": {"type": "number"}},
        "intensities": {"type": "array", "items": {"type": "number"}}},
    "foxglove.CompressedImage": {
        "timestamp": TIME, "frame_id": {"type": "string"}, "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"}},
    "foxglove.LocationFix": {
        "timestamp": TIME, "frame_id": {"type": "string"}, "latitude": {"type": "number"}, "longitude": {"type": "number"},
        "altitude": {"type": "number"},
        "position_covariance": {"type": "array", "items": {"type": "number"}, "minItems": 9, "maxItems": 9},
        "position_covariance_type": {"enum": [0, 1, 2, 3]}},
    "foxglove.PoseInFrame": {"timestamp": TIME, "frame_id": {"type": "string"}, "pose": POSE},
}
FOXGLOVE_SCHEMA_OF: dict[type, str] = {messages.Scan: "foxglove.LaserScan", messages.Frame: "foxglove.CompressedImage",
                                       messages.GnssFix: "foxglove.LocationFix", messages.PoseEstimate: "foxglove.PoseInFrame"}
MESSAGE_TYPES: dict[str, type] = {cls.__name__: cls for cls in (
    messages.Scan, messages.Frame, messages.ImuSample, messages.GnssFix, messages.LandmarkSightings,
    messages.FlowField, messages.PoseEstimate, messages.AttitudeEstimate, messages.RangeEstimate)}


def _schema_of_type(hint: Any) -> dict[str, Any]:
    """The JSON Schema of one dataclass field's exact encoding, from its type hint."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        return {"anyOf": [_schema_of_type(a) for a in typing.get_args(hint)]}
    if origin is typing.Literal:
        return {"enum": list(typing.get_args(hint))}
    if origin is tuple:
        return {"type": "array", "items": _schema_of_type(typing.get_args(hint)[0])}
    if origin is dict:
        return {"type": "object"}
    return {float: NUMBER, int: {"type": "integer"}, bool: {"type": "boolean"}, str: {"type": "string"},
            type(None): {"type": "null"}, np.ndarray: ARRAY}[hint]


def dataclass_properties(cls: type) -> tuple[dict[str, Any], list[str]]:
    """(properties, required) of the exact encoding of dataclass ``cls``'s fields."""
    hints = _hints(cls)
    fields = dataclasses.fields(cls)
    properties = {f.name: _schema_of_type(hints[f.name]) for f in fields}
    required = [f.name for f in fields if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
    return properties, required


def message_schema(cls: type) -> tuple[str, dict[str, Any]]:
    """(schema name, JSON Schema) of a typed message as the recorder writes it."""
    properties, required = dataclass_properties(cls)
    if cls is messages.Frame:
        del properties["image"]  # the image travels as the CompressedImage's PNG data
        required.remove("image")
        properties["shape"] = {"type": "array", "items": {"type": "integer"}}
        required.append("shape")
    if cls is messages.Scan:
        del properties["ranges_m"]  # Foxglove's ranges, with the replaced beams' values beside them
        required.remove("ranges_m")
        properties["replaced_index"] = properties["replaced_ranges_m"] = ARRAY
        required += ["replaced_index", "replaced_ranges_m"]
    name = FOXGLOVE_SCHEMA_OF.get(cls)
    if name is not None:
        properties = {**FOXGLOVE_FIELDS[name], **properties}
        required = [*FOXGLOVE_FIELDS[name], *required]
    else:
        name = f"companion.{cls.__name__}"
    return name, {"title": name, "description": (cls.__doc__ or "").strip().split("\n\n")[0],
                  "type": "object", "properties": properties, "required": required}


def event_schema(name: str, description: str, properties: dict[str, Any] | None = None) -> dict[str, Any]:
    """A schema for a recorder event (no typed message behind it): object with ``properties``."""
    schema: dict[str, Any] = {"title": name, "description": description, "type": "object"}
    if properties is not None:
        schema["properties"] = properties
        schema["required"] = list(properties)
    return schema


# -- values ------------------------------------------------------------------------------------

def exact(value: Any) -> Any:
    """``value`` as JSON that :func:`unexact` turns back into an equal value (see the module doc)."""
    if isinstance(value, np.ndarray):
        return {"dtype": value.dtype.str, "shape": list(value.shape),
                "base64": base64.b64encode(np.ascontiguousarray(value).tobytes()).decode()}
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (list, tuple)):
        return [exact(v) for v in value]
    if isinstance(value, dict):
        return {str(k): exact(v) for k, v in value.items()}
    if value is None or isinstance(value, str):
        return value
    raise TypeError(f"cannot record a {type(value).__name__}")


def unexact(value: Any) -> Any:
    """The value :func:`exact` encoded (lists come back as tuples: the messages' sequences are)."""
    if isinstance(value, str):
        return NON_FINITE.get(value, value)
    if isinstance(value, list):
        return tuple(unexact(v) for v in value)
    if isinstance(value, dict):
        if value.keys() == {"dtype", "shape", "base64"}:
            raw = base64.b64decode(value["base64"])
            return np.frombuffer(raw, dtype=np.dtype(value["dtype"])).reshape(value["shape"]).copy()
        return {k: unexact(v) for k, v in value.items()}
    return value


def stamp(t: float) -> dict[str, int]:
    """A daemon-clock time (s) as Foxglove's ``{sec, nsec}``."""
    ns = max(0, int(round(t * 1e9)))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _pose(position: tuple[float, float, float], euler: tuple[float, float, float]) -> dict[str, Any]:
    q = quat_from_euler(*euler)  # w, x, y, z
    finite = lambda v: float(v) if math.isfinite(v) else 0.0  # noqa: E731 (Foxglove's fields are plain numbers)
    return {"position": {"x": finite(position[0]), "y": finite(position[1]), "z": finite(position[2])},
            "orientation": {"x": finite(q[1]), "y": finite(q[2]), "z": finite(q[3]), "w": finite(q[0])}}


# -- messages ----------------------------------------------------------------------------------

def encode_message(msg: Any, frame_id: str = "") -> dict[str, Any]:
    """The JSON document of a typed message: its exact fields (``image``: PNG in ``data``) plus the
    Foxglove fields of its well-known schema, if it has one. ``frame_id``: the sensor's name."""
    doc = {f.name: exact(getattr(msg, f.name)) for f in dataclasses.fields(msg) if f.name not in ("image", "ranges_m")}
    if isinstance(msg, messages.Scan):
        kept = msg.valid & np.isfinite(msg.ranges_m)
        ranges = np.where(kept, msg.ranges_m, 0.0)
        replaced = np.flatnonzero(~kept).astype(np.int32)
        doc.update(replaced_index=exact(replaced), replaced_ranges_m=exact(msg.ranges_m[replaced].astype(np.float64)))
        # Foxglove's angles turn counter-clockwise about z up; ours clockwise about z down (FRD): the
        # same bearings, with y mirrored, so Foxglove draws the scan upside down unless given this
        # pose: a half turn about x (FRD -> FLU).
        doc.update(timestamp=stamp(msg.t_capture), frame_id=frame_id or msg.sensor_id,
                   pose={"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 1.0, "y": 0.0, "z": 0.0, "w": 0.0}},
                   start_angle=float(msg.angles_rad[0]) if msg.angles_rad.size else 0.0,
                   end_angle=float(msg.angles_rad[-1]) if msg.angles_rad.size else 0.0,
                   ranges=ranges.tolist(), intensities=[])
    elif isinstance(msg, messages.Frame):
        ok, png = cv2.imencode(".png", msg.image)
        if not ok:
            raise ValueError(f"PNG encoding of a {msg.image.shape} image failed")
        doc.update(timestamp=stamp(msg.t_capture), frame_id=frame_id or msg.camera_id,
                   data=base64.b64encode(png.tobytes()).decode(), format="png", shape=list(msg.image.shape))
    elif isinstance(msg, messages.GnssFix):
        h = msg.h_acc_m if msg.h_acc_m is not None and math.isfinite(msg.h_acc_m) else None
        v = msg.v_acc_m if msg.v_acc_m is not None and math.isfinite(msg.v_acc_m) else None
        cov = [0.0] * 9
        if h is not None and v is not None:
            cov[0] = cov[4] = h * h
            cov[8] = v * v
        finite = lambda x: float(x) if math.isfinite(x) else 0.0  # noqa: E731
        doc.update(timestamp=stamp(msg.t_capture), frame_id=frame_id or msg.receiver_id, latitude=finite(msg.lat_deg),
                   longitude=finite(msg.lon_deg), altitude=finite(msg.alt_m), position_covariance=cov,
                   position_covariance_type=2 if h is not None and v is not None else 0)
    elif isinstance(msg, messages.PoseEstimate):
        doc.update(timestamp=stamp(msg.t_capture), frame_id=FRAME_ID_WORLD,
                   pose=_pose(tuple(msg.position_ned), msg.euler_rad))
    return doc


def decode_message(cls: type, doc: dict[str, Any]) -> Any:
    """The typed message :func:`encode_message` wrote (its Foxglove fields are ignored)."""
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name == "ranges_m" and cls is messages.Scan:
            ranges = np.array(doc["ranges"], dtype=np.float64)
            ranges[unexact(doc["replaced_index"])] = unexact(doc["replaced_ranges_m"])
            kwargs["ranges_m"] = ranges
        elif f.name == "image":
            png = np.frombuffer(base64.b64decode(doc["data"]), dtype=np.uint8)
            flag = cv2.IMREAD_COLOR if len(doc["shape"]) == 3 else cv2.IMREAD_GRAYSCALE
            kwargs["image"] = cv2.imdecode(png, flag)
        elif f.name in doc:
            kwargs[f.name] = _field_value(cls, f.name, doc[f.name])
    return cls(**kwargs)


def _field_value(cls: type, name: str, value: Any) -> Any:
    """A field's value from its exact encoding; a text field stays text (a sensor named "inf")."""
    return value if _hints(cls)[name] is str else unexact(value)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def encode_estimate(estimate: messages.Estimate) -> dict[str, Any]:
    """An estimate inside a nav-cycle record: its exact fields and its ``type``."""
    return {"type": type(estimate).__name__, **{f.name: exact(getattr(estimate, f.name))
                                                for f in dataclasses.fields(estimate)}}


def decode_estimate(doc: dict[str, Any]) -> messages.Estimate:
    cls = MESSAGE_TYPES[doc["type"]]
    return cls(**{f.name: _field_value(cls, f.name, doc[f.name]) for f in dataclasses.fields(cls) if f.name in doc})


def dumps(doc: dict[str, Any]) -> bytes:
    """A document as compact JSON bytes (strict: a NaN left in it is a bug, raised here)."""
    return json.dumps(doc, allow_nan=False, separators=(",", ":")).encode()
