"""What the flight recorder writes: each typed message (companion/messages.py) as one JSON
document with a JSON Schema, exact both ways, and readable by Foxglove with no plug-in.

Exactness: a message decoded from its document equals the one encoded, bit for bit (floats are
written with Python's shortest round-trip repr; a non-finite float as the string ``"nan"``,
``"inf"`` or ``"-inf"``; a numpy array as ``{"dtype", "shape", "base64"}``, its raw bytes, which is
also some 40 times cheaper than a JSON list of floats; a camera image as lossless PNG). This is
what makes ``companion replay`` deterministic. Two arrays have a compact form, used only where it
decodes to the very same bits: a bool array as packed bits (``"bits"``, a scan's valid mask), and
a float64 array of whole millimetres (``"mm_dtype"``, ``"mm"``: the integers, decoded as
``int / 1000.0``; a Hokuyo's ranges, which SCIP gives in mm) in 2 or 4 bytes a value.

Foxglove: a camera frame, a GNSS fix and a pose are written as Foxglove's well-known schema
(``foxglove.CompressedImage``, ``foxglove.LocationFix``, ``foxglove.PoseInFrame``: its fields, its
name) with the exact fields added beside them (JSON Schema allows extra properties, Foxglove
ignores them). A scan's Foxglove view is a twin message, ``foxglove.LaserScan`` in protobuf
(:func:`laser_scan_view`, encoded by the Foxglove SDK: its ranges are raw doubles, where JSON would
cost 1.5 ms a scan). The rest are ``companion.<Type>`` schemas generated from the dataclasses.
Foxglove's ``timestamp`` is the daemon's monotonic clock (s since its boot, not the Unix epoch),
the time base of every stamp in the recording.
"""

from __future__ import annotations

import base64
import dataclasses
import functools
import math
import types
import typing
from dataclasses import dataclass
from typing import Any

import cv2
import foxglove.messages as foxglove_messages
import numpy as np
import orjson

from companion import messages
from companion.frames import quat_from_euler

SCHEMA_ENCODING = "jsonschema"
MESSAGE_ENCODING = "json"
NON_FINITE = {"nan": math.nan, "inf": math.inf, "-inf": -math.inf}
FRAME_ID_WORLD = "local_ned"  # MAVLink LOCAL_NED at the autopilot's EKF origin

# -- JSON Schema building blocks ------------------------------------------------------------

NUMBER: dict[str, Any] = {"anyOf": [{"type": "number"}, {"enum": list(NON_FINITE)}]}
_DTYPE = {"type": "string", "description": "numpy dtype string, byte order included (e.g. <f8)"}
_SHAPE = {"type": "array", "items": {"type": "integer", "minimum": 0}}
ARRAY: dict[str, Any] = {"oneOf": [
    {"type": "object", "required": ["dtype", "shape", "base64"], "additionalProperties": False,
     "properties": {"dtype": _DTYPE, "shape": _SHAPE,
                    "base64": {"type": "string", "contentEncoding": "base64", "description": "the C-order bytes"}}},
    {"type": "object", "required": ["dtype", "shape", "bits"], "additionalProperties": False,
     "properties": {"dtype": {"const": "|b1"}, "shape": _SHAPE,
                    "bits": {"type": "string", "contentEncoding": "base64",
                             "description": "a bool array's values in C order, 8 a byte, first value in the high bit "
                                            "(numpy.packbits)"}}},
    {"type": "object", "required": ["dtype", "shape", "mm_dtype", "mm"], "additionalProperties": False,
     "properties": {"dtype": {"const": "<f8"}, "shape": _SHAPE, "mm_dtype": {"enum": ["<u2", "<i4"]},
                    "mm": {"type": "string", "contentEncoding": "base64",
                           "description": "float64 values that are whole thousandths (a range in mm): the integers "
                                          "value * 1000 in C order, as mm_dtype; each value is integer / 1000.0"}}}]}
MM_MIN_SIZE = 64  # float64 arrays from this many values are tried as whole millimetres (scans, not covariances)
TIME: dict[str, Any] = {
    "type": "object", "required": ["sec", "nsec"],
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}}}
_XYZ = {"type": "object", "required": ["x", "y", "z"], "properties": {k: {"type": "number"} for k in "xyz"}}
_XYZW = {"type": "object", "required": ["x", "y", "z", "w"], "properties": {k: {"type": "number"} for k in "xyzw"}}
POSE: dict[str, Any] = {"type": "object", "required": ["position", "orientation"],
                        "properties": {"position": _XYZ, "orientation": _XYZW}}


@dataclass(frozen=True)
class ChannelSchema:
    """A channel's schema as MCAP and the Foxglove protocol take it: name, schema encoding and data,
    and the encoding of the channel's messages."""

    name: str
    encoding: str  # "jsonschema" or "protobuf"
    data: bytes  # the JSON Schema, or a protobuf FileDescriptorSet
    message_encoding: str  # "json" or "protobuf"


def json_schema(name: str, body: dict[str, Any]) -> ChannelSchema:
    return ChannelSchema(name, SCHEMA_ENCODING, dumps(body), MESSAGE_ENCODING)


# The fields of Foxglove's well-known schemas we fill (https://docs.foxglove.dev/docs/visualization/message-schemas)
FOXGLOVE_FIELDS: dict[str, dict[str, Any]] = {
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
FOXGLOVE_SCHEMA_OF: dict[type, str] = {messages.Frame: "foxglove.CompressedImage", messages.GnssFix: "foxglove.LocationFix",
                                       messages.PoseEstimate: "foxglove.PoseInFrame"}
_LASER_SCAN = foxglove_messages.LaserScan.get_schema()
LASER_SCAN_SCHEMA = ChannelSchema(_LASER_SCAN.name, _LASER_SCAN.encoding, bytes(_LASER_SCAN.data), "protobuf")
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


@functools.cache
def message_schema(cls: type) -> ChannelSchema:
    """The JSON Schema of a typed message as the recorder writes it (see :func:`schema_body`)."""
    name, body = schema_body(cls)
    return json_schema(name, body)


def schema_body(cls: type) -> tuple[str, dict[str, Any]]:
    """(schema name, JSON Schema) of a typed message as the recorder writes it."""
    properties, required = dataclass_properties(cls)
    if cls is messages.Frame:
        del properties["image"]  # the image travels as the CompressedImage's PNG data
        required.remove("image")
        properties["shape"] = {"type": "array", "items": {"type": "integer"}}
        required.append("shape")
    name = FOXGLOVE_SCHEMA_OF.get(cls)
    if name is not None:
        properties = {**FOXGLOVE_FIELDS[name], **properties}
        required = [*FOXGLOVE_FIELDS[name], *required]
    else:
        name = f"companion.{cls.__name__}"
    return name, {"title": name, "description": (cls.__doc__ or "").strip().split("\n\n")[0],
                  "type": "object", "properties": properties, "required": required}


def event_schema(name: str, description: str, properties: dict[str, Any] | None = None) -> ChannelSchema:
    """The JSON Schema of a recorder event (no typed message behind it): object with ``properties``."""
    schema: dict[str, Any] = {"title": name, "description": description, "type": "object"}
    if properties is not None:
        schema["properties"] = properties
        schema["required"] = list(properties)
    return json_schema(name, schema)


# -- values ------------------------------------------------------------------------------------

def exact(value: Any) -> Any:
    """``value`` as JSON that :func:`unexact` turns back into an equal value (see the module doc)."""
    kind = type(value)
    if kind is str or kind is int or kind is bool or value is None:
        return value
    if kind is float:
        return _exact_float(value)
    if kind is np.ndarray:
        return _exact_array(value)
    if isinstance(value, (float, np.floating)):
        return _exact_float(float(value))
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


def _exact_array(value: np.ndarray) -> dict[str, Any]:
    """An array's exact encoding: packed bits for bool, integer millimetres for a float64 array
    whose values all are (and decode to the same bits), else its raw bytes (see the module doc)."""
    shape = list(value.shape)
    if value.dtype == np.bool_:
        return {"dtype": "|b1", "shape": shape, "bits": _b64(np.packbits(value, axis=None))}
    if value.dtype == np.float64 and value.size >= MM_MIN_SIZE:
        mm = _whole_millimetres(value)
        if mm is not None:
            return {"dtype": "<f8", "shape": shape, "mm_dtype": mm.dtype.str, "mm": _b64(mm)}
    return {"dtype": value.dtype.str, "shape": shape, "base64": _b64(value)}


def _whole_millimetres(value: np.ndarray) -> np.ndarray | None:
    """``value * 1000`` as little-endian uint16 or int32 if every value is a whole millimetre that
    ``integer / 1000.0`` gives back bit for bit (a negative zero or a NaN is not), else None."""
    flat = value.reshape(-1)
    for v in (flat.item(0), flat.item(-1)):  # most arrays that are not (a scan's angles) fail here, cheaply
        if not math.isfinite(v * 1000.0) or round(v * 1000.0) / 1000.0 != v:
            return None
    with np.errstate(invalid="ignore", over="ignore"):  # NaN, inf and out-of-range values fail the round trip
        ints = np.rint(flat * 1000.0).astype("<i4")
    if not np.array_equal((ints / 1000.0).view(np.int64), flat.view(np.int64)):  # float64 bits, the caller's check
        return None
    return ints.astype("<u2") if 0 <= ints.min() and ints.max() <= 0xFFFF else ints


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode()


def _exact_float(v: float) -> float | str:
    return v if math.isfinite(v) else ("nan" if math.isnan(v) else ("inf" if v > 0 else "-inf"))


def unexact(value: Any) -> Any:
    """The value :func:`exact` encoded (lists come back as tuples: the messages' sequences are)."""
    if isinstance(value, str):
        return NON_FINITE.get(value, value)
    if isinstance(value, list):
        return tuple(unexact(v) for v in value)
    if isinstance(value, dict):
        keys = value.keys()
        if keys == {"dtype", "shape", "base64"}:
            raw = base64.b64decode(value["base64"])
            return np.frombuffer(raw, dtype=np.dtype(value["dtype"])).reshape(value["shape"]).copy()
        if keys == {"dtype", "shape", "bits"}:
            count = math.prod(value["shape"])
            bits = np.unpackbits(np.frombuffer(base64.b64decode(value["bits"]), dtype=np.uint8), count=count)
            return bits.astype(bool).reshape(value["shape"])
        if keys == {"dtype", "shape", "mm_dtype", "mm"}:
            ints = np.frombuffer(base64.b64decode(value["mm"]), dtype=np.dtype(value["mm_dtype"]))
            return (ints / 1000.0).reshape(value["shape"])
        return {k: unexact(v) for k, v in value.items()}
    return value


def stamp(t: float) -> dict[str, int]:
    """A daemon-clock time (s) as Foxglove's ``{sec, nsec}``."""
    ns = max(0, int(round(t * 1e9)))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _pose(position: tuple[float, float, float], euler: tuple[float, float, float]) -> dict[str, Any]:
    q = quat_from_euler(*euler)  # w, x, y, z
    return {"position": {"x": _plain(position[0]), "y": _plain(position[1]), "z": _plain(position[2])},
            "orientation": {"x": _plain(q[1]), "y": _plain(q[2]), "z": _plain(q[3]), "w": _plain(q[0])}}


def _plain(x: float) -> float:
    """A value for one of Foxglove's plain-number fields: a non-finite one as 0 (the exact value
    is in the message's own fields)."""
    return float(x) if math.isfinite(x) else 0.0


# -- messages ----------------------------------------------------------------------------------

def encode_message(msg: Any, frame_id: str = "") -> dict[str, Any]:
    """The JSON document of a typed message: its exact fields (``image``: PNG in ``data``) plus the
    Foxglove fields of its well-known schema, if it has one. ``frame_id``: the sensor's name."""
    doc = {f.name: exact(getattr(msg, f.name)) for f in dataclasses.fields(msg) if f.name != "image"}
    if isinstance(msg, messages.Frame):
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
        doc.update(timestamp=stamp(msg.t_capture), frame_id=frame_id or msg.receiver_id, latitude=_plain(msg.lat_deg),
                   longitude=_plain(msg.lon_deg), altitude=_plain(msg.alt_m), position_covariance=cov,
                   position_covariance_type=2 if h is not None and v is not None else 0)
    elif isinstance(msg, messages.PoseEstimate):
        doc.update(timestamp=stamp(msg.t_capture), frame_id=FRAME_ID_WORLD,
                   pose=_pose(tuple(msg.position_ned), msg.euler_rad))
    return doc


def decode_message(cls: type, doc: dict[str, Any]) -> Any:
    """The typed message :func:`encode_message` wrote (its Foxglove fields are ignored)."""
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name == "image":
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


def laser_scan_view(scan: messages.Scan, frame_id: str) -> bytes:
    """A scan as Foxglove's ``foxglove.LaserScan`` (protobuf): what Foxglove draws with no plug-in.
    An invalid beam's range is NaN (Foxglove draws no point). Foxglove's angles turn counter-clockwise
    about z up, ours clockwise about z down (FRD): the pose, a half turn about x (FRD -> FLU), draws
    the scan the right way up. The beams are taken as evenly spaced from the first to the last angle,
    as the schema says."""
    t = stamp(scan.t_capture)
    ranges = np.where(scan.valid, scan.ranges_m, np.nan)
    angles = scan.angles_rad
    return foxglove_messages.LaserScan(
        timestamp=foxglove_messages.Timestamp(sec=t["sec"], nsec=t["nsec"]), frame_id=frame_id,
        pose=foxglove_messages.Pose(position=foxglove_messages.Vector3(x=0.0, y=0.0, z=0.0),
                                    orientation=foxglove_messages.Quaternion(x=1.0, y=0.0, z=0.0, w=0.0)),
        start_angle=float(angles[0]) if angles.size else 0.0, end_angle=float(angles[-1]) if angles.size else 0.0,
        ranges=ranges.tolist(), intensities=[]).encode()


def encode_estimate(estimate: messages.Estimate) -> dict[str, Any]:
    """An estimate inside a nav-cycle record: its exact fields and its ``type``."""
    return {"type": type(estimate).__name__, **{f.name: exact(getattr(estimate, f.name))
                                                for f in dataclasses.fields(estimate)}}


def decode_estimate(doc: dict[str, Any]) -> messages.Estimate:
    cls = MESSAGE_TYPES[doc["type"]]
    return cls(**{f.name: _field_value(cls, f.name, doc[f.name]) for f in dataclasses.fields(cls) if f.name in doc})


def dumps(doc: dict[str, Any]) -> bytes:
    """A document as compact JSON bytes (orjson: some 50x faster than the json module on a scan's
    document, most of the writer thread's time before). Its numbers come from :func:`exact` and
    :func:`_plain`, so they are finite: orjson would write a NaN as null, not raise."""
    return orjson.dumps(doc)
