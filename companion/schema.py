"""Typed YAML loading: YAML text -> dataclass instances, with file/key/line in every error.

A schema is a tree of dataclasses. Each field's type drives the conversion (int, float, bool,
str, Literal, Optional, list, tuple, dict[str, X], nested dataclass); a field without a default
is required. A dataclass may define ``validate(self) -> (relative key path, message) | None``
for checks across fields; the path (e.g. ``walls[4].end``) locates the error's line. ``field(metadata=meta(doc=..., range=(lo, hi)))`` adds the one-line documentation
used by the generated config reference and an inclusive numeric range.

Errors raise :class:`SchemaError` naming the file, the dotted key path and the 1-based line of
the offending node, e.g. ``config/sitl.yaml:12: mavlink.estimate_rate_hz: must be within
[1, 100], got 500``.

Files come in through :func:`read_regular_file`, the one reader of user-supplied files (configs,
missions, worlds, signing keys, recordings): regular files only, never more than a cap, so a
FIFO, /dev/zero or a huge file is an error, not a hang. A YAML file must be UTF-8 text (else the
error names the line of the first bad byte) whose top level is a mapping.
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import math
import os
import re
import stat
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin, get_type_hints

import yaml

T = TypeVar("T")

YAML_MAX_BYTES = 1 << 20  # config, mission and world files (the shipped ones are a few KiB)
MAX_VALUES = 200_000  # values built from one document, aliases counted at each use (a "billion laughs" stops here)
TOO_DEEP = "lists or mappings nested too deeply"
_COMPOSER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml when present: several times faster


class SchemaError(Exception):
    """A document does not match its schema; ``str()`` is ``file:line: key.path: message``, without
    the key path for a problem of the document as a whole (``file:line: message``) and without the
    line when there is none (the file cannot be read: ``file: message``)."""

    def __init__(self, file: str, key_path: str, line: int | None, message: str) -> None:
        self.file = file
        self.key_path = key_path
        self.line = line
        self.message = message
        where = f"{file}:{line}" if line is not None else file
        super().__init__(f"{where}: {key_path}: {message}" if key_path else f"{where}: {message}")


def meta(doc: str, range: tuple[float, float] | None = None, rest: bool = False) -> dict[str, Any]:
    """Field metadata: a one-line description and an optional inclusive numeric range.

    ``rest=True`` (one ``dict[str, Any]`` field per dataclass) collects every key the dataclass
    does not name, as plain values, for the dataclass's ``validate`` to check (e.g. the
    pipeline sections, typed by the pipeline registry)."""
    return {"doc": doc, "range": range, "rest": rest}


def read_regular_file(path: str | Path, max_bytes: int) -> bytes:
    """The whole content of the regular file at ``path``, at most ``max_bytes`` long.

    Never blocks and never holds more than ``max_bytes`` + 1 bytes: a FIFO, a device such as
    /dev/zero, a directory or a socket is refused before it is read, and reading stops one byte
    past the cap. Raises OSError whose ``strerror`` says why in words (the system's reason when
    the file cannot be opened, else what the file is or that it is too large).
    """
    _require_regular(os.stat(path))  # before open(): opening a device can have effects (serial DTR)
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # a FIFO swapped in cannot block it
    try:
        _require_regular(os.fstat(fd))
        chunks: list[bytes] = []
        left = max_bytes + 1
        while left > 0 and (chunk := os.read(fd, min(left, 1 << 16))):
            chunks.append(chunk)
            left -= len(chunk)
    finally:
        os.close(fd)
    data = b"".join(chunks)
    if len(data) > max_bytes:
        raise OSError(errno.EFBIG, f"larger than {max_bytes} bytes, the limit for this file")
    return data


def _require_regular(st: os.stat_result) -> None:
    """OSError unless ``st`` is a regular file's."""
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _FILE_KINDS if test(st.st_mode)), "another kind of file")
        raise OSError(errno.EINVAL, f"not a regular file but {kind}")


_FILE_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
               (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


@dataclasses.dataclass(frozen=True)
class Document:
    """A parsed YAML document whose top level is a mapping: its file name (for messages) and its
    root node, which knows the line of every key."""

    file: str
    root: yaml.MappingNode

    def line_of(self, key_path: str) -> int:
        """The 1-based line of the key at ``key_path`` (e.g. ``mission.file``, ``walls[4].end``);
        for a key not written in the file, the line of its deepest enclosing node that is."""
        return _line(_find_node(self.root, key_path))

    def build(self, schema: type[T]) -> T:
        """``schema`` built from this document; SchemaError (this file, key path, line) if it does not match."""
        try:
            return _Builder(self.file).build(schema, self.root, "")
        except RecursionError:
            raise SchemaError(self.file, "", 1, TOO_DEEP) from None


def load_file(path: str | Path, schema: type[T]) -> T:
    """Read the YAML file at ``path`` (see :func:`read_document`) and build ``schema`` from it."""
    return read_document(path).build(schema)


def load_text(text: str, schema: type[T], file: str = "<string>") -> T:
    """Build ``schema`` from YAML ``text``; ``file`` is only used in error messages."""
    return parse_document(text, file).build(schema)


def read_document(path: str | Path) -> Document:
    """The YAML document in the file at ``path``: a regular file of at most :data:`YAML_MAX_BYTES`
    of UTF-8 text whose top level is a mapping; SchemaError naming the file (and the line, for its
    content) otherwise."""
    file = str(path)
    try:
        data = read_regular_file(path, YAML_MAX_BYTES)
    except OSError as exc:
        raise SchemaError(file, "", None, f"cannot read file: {exc.strerror or exc}") from exc
    return parse_document(_decode_utf8(data, file), file)


def parse_document(text: str, file: str = "<string>") -> Document:
    """The YAML document in ``text``; SchemaError (``file``, line) if it is not YAML, is empty or
    its top level is not a mapping."""
    try:
        node = yaml.compose(text, Loader=_COMPOSER)
    except yaml.YAMLError as exc:
        line, problem = _yaml_problem(exc, text)
        raise SchemaError(file, "", line, f"invalid YAML: {problem}") from exc
    except RecursionError:
        raise SchemaError(file, "", 1, TOO_DEEP) from None
    if node is None:
        raise SchemaError(file, "", 1, "empty document: expected a mapping of keys")
    if not isinstance(node, yaml.MappingNode):
        raise SchemaError(file, "", _line(node), f"expected a mapping of keys, got {_describe(node)}")
    return Document(file, node)


def _decode_utf8(data: bytes, file: str) -> str:
    """``data`` as UTF-8 text; SchemaError at the line of the first byte that is not."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line_start = data.rfind(b"\n", 0, exc.start) + 1
        raise SchemaError(file, "", data.count(b"\n", 0, exc.start) + 1,
                          f"not UTF-8 text: byte 0x{data[exc.start]:02x} at column {exc.start - line_start + 1}"
                          ) from None


def _yaml_problem(exc: yaml.YAMLError, text: str) -> tuple[int | None, str]:
    """(1-based line or None, what is wrong) of a YAML parse error."""
    if isinstance(exc, yaml.reader.ReaderError):  # a character YAML does not allow (NUL, control)
        # libyaml counts the position in bytes of UTF-8, PyYAML's own reader in characters
        before = text.encode("utf-8")[:exc.position].decode("utf-8", "ignore") if _COMPOSER is not yaml.SafeLoader \
            else text[:exc.position]
        return before.count("\n") + 1, f"character #x{exc.character:04x} is not allowed"
    mark = getattr(exc, "problem_mark", None)
    return (mark.line + 1 if mark is not None else None), getattr(exc, "problem", None) or str(exc)


def _line(node: yaml.Node) -> int:
    return node.start_mark.line + 1


class _Builder:
    def __init__(self, file: str) -> None:
        self.file = file
        self.values = 0  # built so far: an alias is built again at every use

    def error(self, node: yaml.Node, path: str, message: str) -> SchemaError:
        return SchemaError(self.file, path, _line(node), message)

    def build(self, tp: Any, node: yaml.Node, path: str) -> Any:
        self.values += 1
        if self.values > MAX_VALUES:
            raise self.error(node, path, f"more than {MAX_VALUES} values (aliases count at every use)")
        origin = get_origin(tp)
        if dataclasses.is_dataclass(tp):
            return self._dataclass(tp, node, path)
        if origin in (typing.Union, types.UnionType):
            return self._union(tp, node, path)
        if origin is Literal:
            value = self._scalar(node, path)
            if value not in get_args(tp):
                allowed = ", ".join(repr(a) for a in get_args(tp))
                raise self.error(node, path, f"must be one of {allowed}, got {value!r}")
            return value
        if origin is list:
            return [self.build(get_args(tp)[0], item, f"{path}[{i}]")
                    for i, item in enumerate(self._sequence(node, path))]
        if origin is tuple:
            return self._tuple(tp, node, path)
        if origin is dict:
            key_tp, value_tp = get_args(tp)
            return {k: self.build(value_tp, v, f"{path}.{k}" if path else k)
                    for k, v in self._mapping(node, path, key_tp).items()}
        if tp is Any:
            try:
                return _plain(node)
            except yaml.YAMLError as exc:  # a recursive alias (&a [*a])
                raise self.error(node, path, getattr(exc, "problem", None) or str(exc)) from exc
        if tp in (int, float, bool, str):
            return self._primitive(tp, node, path)
        raise TypeError(f"schema type {tp!r} at {path} is not supported")

    def _dataclass(self, cls: Any, node: yaml.Node, path: str) -> Any:
        items = self._mapping(node, path, str)
        hints = _type_hints(cls)
        fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
        rest = next((f.name for f in fields.values() if (f.metadata or {}).get("rest")), None)
        kwargs: dict[str, Any] = {}
        for key, value_node in items.items():
            if key in fields and key != rest:
                continue
            if rest is None:
                known = ", ".join(sorted(fields))
                raise self.error(_key_node(node, key), _join(path, key),
                                 f"unknown key (known keys: {known})")
            kwargs.setdefault(rest, {})[key] = self.build(Any, value_node, _join(path, key))
        for name, f in fields.items():
            if name == rest:
                continue
            sub = _join(path, name)
            if name in items:
                value = self.build(hints[name], items[name], sub)
                self._check_range(f, value, items[name], sub)
                kwargs[name] = value
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise self.error(node, sub, "required key is missing")
        instance = cls(**kwargs)
        post = getattr(instance, "validate", None)
        if post is not None:
            problem = post()
            if problem is not None:
                key, message = problem
                raise self.error(_find_node(node, key), _join(path, key), message)
        return instance

    def _check_range(self, f: dataclasses.Field, value: Any, node: yaml.Node, path: str) -> None:
        bounds = f.metadata.get("range") if f.metadata else None
        if bounds is None or value is None:
            return
        values = value if isinstance(value, (list, tuple)) else [value]
        lo, hi = bounds
        for v in values:
            if not (lo <= v <= hi):
                raise self.error(node, path, f"must be within [{lo:g}, {hi:g}], got {v!r}")

    def _union(self, tp: Any, node: yaml.Node, path: str) -> Any:
        args = get_args(tp)
        if type(None) in args and _is_null(node):
            return None
        candidates = [a for a in args if a is not type(None)]
        if len(candidates) == 1:
            return self.build(candidates[0], node, path)
        errors = []
        for candidate in candidates:
            try:
                return self.build(candidate, node, path)
            except SchemaError as exc:
                errors.append(exc.message)
        raise self.error(node, path, " or ".join(errors))

    def _tuple(self, tp: Any, node: yaml.Node, path: str) -> tuple:
        args = get_args(tp)
        items = self._sequence(node, path)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(self.build(args[0], it, f"{path}[{i}]") for i, it in enumerate(items))
        if len(items) != len(args):
            raise self.error(node, path, f"expected a list of {len(args)} values, got {len(items)}")
        return tuple(self.build(a, it, f"{path}[{i}]") for i, (a, it) in enumerate(zip(args, items)))

    def _mapping(self, node: yaml.Node, path: str, key_tp: Any) -> dict[str, yaml.Node]:
        if not isinstance(node, yaml.MappingNode):
            raise self.error(node, path, f"expected a mapping, got {_describe(node)}")
        out: dict[str, yaml.Node] = {}
        for key_node, value_node in node.value:
            key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
            if key_tp is str and not isinstance(key, str):
                raise self.error(key_node, path, "mapping keys must be strings")
            if key in out:
                raise self.error(key_node, _join(path, key), "duplicate key")
            out[key] = value_node
        return out

    def _sequence(self, node: yaml.Node, path: str) -> list[yaml.Node]:
        if not isinstance(node, yaml.SequenceNode):
            raise self.error(node, path, f"expected a list, got {_describe(node)}")
        return list(node.value)

    def _scalar(self, node: yaml.Node, path: str) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            raise self.error(node, path, f"expected a single value, got {_describe(node)}")
        return _plain(node)

    def _primitive(self, tp: type, node: yaml.Node, path: str) -> Any:
        value = self._scalar(node, path)
        if tp is float and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        if tp is float and isinstance(value, float) and not math.isfinite(value):
            raise self.error(node, path, f"must be a finite number, got {value!r}")
        if not isinstance(value, tp) or (tp is int and isinstance(value, bool)):
            raise self.error(node, path, f"expected {_type_name(tp)}, got {_describe(node)}")
        return value


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    """``get_type_hints(cls)``, evaluated once per class: it is most of the time a build takes."""
    return get_type_hints(cls)


def _plain(node: yaml.Node) -> Any:
    loader = yaml.SafeLoader("")
    try:
        return loader.construct_object(node, deep=True)
    finally:
        loader.dispose()


_PATH_TOKEN = re.compile(r"\[(\d+)\]|([^.\[\]]+)")


def _find_node(node: yaml.Node, relative_path: str) -> yaml.Node:
    """The node a relative key path such as ``walls[4].end`` names (the deepest one found).

    For a mapping key that ends the path, the key's own node is returned, so the error points
    at the line where the key is written.
    """
    tokens = _PATH_TOKEN.findall(relative_path)
    for n, (index, key) in enumerate(tokens):
        if index and isinstance(node, yaml.SequenceNode) and int(index) < len(node.value):
            node = node.value[int(index)]
        elif key and isinstance(node, yaml.MappingNode):
            pair = next(((k, v) for k, v in node.value if getattr(k, "value", None) == key), None)
            if pair is None:
                break
            node = pair[0] if n == len(tokens) - 1 else pair[1]
        else:
            break
    return node


def _is_null(node: yaml.Node) -> bool:
    return isinstance(node, yaml.ScalarNode) and node.tag == "tag:yaml.org,2002:null"


def _key_node(mapping: yaml.Node, key: str) -> yaml.Node:
    for key_node, _ in mapping.value:
        if getattr(key_node, "value", None) == key:
            return key_node
    return mapping


def _join(path: str, key: str) -> str:
    return f"{path}.{key}" if path else key


def _type_name(tp: type) -> str:
    return {int: "an integer", float: "a number", bool: "true or false", str: "a string"}[tp]


def _describe(node: yaml.Node) -> str:
    if isinstance(node, yaml.MappingNode):
        return "a mapping"
    if isinstance(node, yaml.SequenceNode):
        return "a list"
    value = _plain(node)
    if value is None:
        return "nothing (null)"
    kind = {bool: "boolean", int: "integer", float: "number", str: "string"}.get(type(value), "value")
    return f"{kind} {value!r}"


def reference_rows(cls: Any, prefix: str = "") -> list[tuple[str, str, str, str]]:
    """(key path, type, default, description) for every key of a schema, depth first.

    Used to generate docs/config.md so the reference can never drift from the code.
    """
    rows: list[tuple[str, str, str, str]] = []
    hints = get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp = hints[f.name]
        path = _join(prefix, "<name>" if (f.metadata or {}).get("rest") else f.name)
        doc = (f.metadata or {}).get("doc", "")
        bounds = (f.metadata or {}).get("range")
        if bounds is not None:
            doc += f" Range [{bounds[0]:g}, {bounds[1]:g}]."
        if f.default is not dataclasses.MISSING:
            default = repr(f.default)
        elif f.default_factory is not dataclasses.MISSING:
            default_value = f.default_factory()
            default = "(see below)" if dataclasses.is_dataclass(default_value) else repr(default_value)
        else:
            default = "required"
        rows.append((path, _type_label(tp), default, doc.strip()))
        if dataclasses.is_dataclass(tp):
            rows.extend(reference_rows(tp, path))
        elif get_origin(tp) is dict and dataclasses.is_dataclass(get_args(tp)[1]):
            rows.extend(reference_rows(get_args(tp)[1], f"{path}.<name>"))
    return rows


def _type_label(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return " \\| ".join(repr(a) for a in get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " \\| ".join(_type_label(a) for a in get_args(tp))
    if origin in (list, tuple, dict):
        inner = ", ".join("..." if a is Ellipsis else _type_label(a) for a in get_args(tp))
        return f"{origin.__name__}[{inner}]"
    if dataclasses.is_dataclass(tp):
        return "mapping"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))
