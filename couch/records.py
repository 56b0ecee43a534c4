"""Dataclasses to and from HDF5 files: the pipeline's cache of stage results.

A record file holds one dataclass instance. Array fields become datasets; nested dataclasses
(and lists of them) become groups; every other field (numbers, strings, paths, lists, dicts of
JSON-able values) goes into the group's ``fields`` attribute as JSON. Reading rebuilds the
instance from the class's type hints, so nothing is unpickled and a file from another version
of a class fails with a clear :class:`RecordError` instead of loading garbage.
"""

from __future__ import annotations

import dataclasses
import json
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import h5py
import numpy as np

from couch.atomic import atomic_path

T = TypeVar("T")
RECORD_VERSION = 1


class RecordError(ValueError):
    """A record file cannot be read as the requested class (the message names the file)."""


def _plain(value: Any) -> Any:
    """A JSON-able copy of a non-array field value."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, float) and not np.isfinite(value):
        return repr(value)  # JSON has no NaN/inf; float("nan") reads it back
    return value


def _write(group: h5py.Group, obj: Any) -> None:
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, np.ndarray):
            if value.dtype == object:
                raise TypeError(f"{type(obj).__name__}.{f.name}: object arrays are not stored")
            group.create_dataset(f.name, data=value, compression="gzip" if value.size >= 4096
                                 else None)
        elif dataclasses.is_dataclass(value):
            _write(group.create_group(f.name), value)
        elif isinstance(value, list) and value and all(dataclasses.is_dataclass(v) for v in value):
            sub = group.create_group(f.name)
            sub.attrs["length"] = len(value)
            for i, v in enumerate(value):
                _write(sub.create_group(str(i)), v)
        else:
            fields[f.name] = _plain(value)
    group.attrs["fields"] = json.dumps(fields)


def write_record(path: str | os.PathLike, obj: Any) -> None:
    """Write dataclass instance ``obj`` to ``path`` atomically (temp file, then replace)."""
    if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        raise TypeError(f"write_record needs a dataclass instance, got {type(obj).__name__}")
    with atomic_path(Path(path)) as tmp, h5py.File(tmp, "w") as h5:
        h5.attrs["record_version"] = RECORD_VERSION
        h5.attrs["class"] = type(obj).__qualname__
        _write(h5, obj)


def _strip_optional(tp: Any) -> Any:
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return rest[0] if len(rest) == 1 else tp
    return tp


def _restore(tp: Any, value: Any) -> Any:
    """Undo :func:`_plain` for a field of type ``tp``."""
    if value is None:
        return None
    tp = _strip_optional(tp)
    origin = typing.get_origin(tp)
    if tp is Path:
        return Path(value)
    if tp is float:
        return float(value)
    if origin is tuple:
        return tuple(value)
    args = typing.get_args(tp)
    if origin is list and args and typing.get_origin(args[0]) is tuple:
        return [tuple(v) for v in value]
    return value


def _read(group: h5py.Group, cls: type, where: str) -> Any:
    hints = typing.get_type_hints(cls)
    try:
        stored = json.loads(group.attrs["fields"])
    except (KeyError, json.JSONDecodeError) as exc:
        raise RecordError(f"{where}: no readable field table ({exc})") from None
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp = _strip_optional(hints[f.name])
        if f.name in group and isinstance(group[f.name], h5py.Dataset):
            values[f.name] = group[f.name][()]
        elif f.name in group:
            sub = group[f.name]
            if typing.get_origin(tp) is list:
                item = typing.get_args(tp)[0]
                values[f.name] = [_read(sub[str(i)], item, f"{where}/{f.name}/{i}")
                                  for i in range(int(sub.attrs["length"]))]
            else:
                values[f.name] = _read(sub, tp, f"{where}/{f.name}")
        elif f.name in stored:
            values[f.name] = _restore(hints[f.name], stored[f.name])
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise RecordError(f"{where}: field '{f.name}' of {cls.__name__} is missing")
    return cls(**values)


def read_record(path: str | os.PathLike, cls: type[T]) -> T:
    """Read a record of dataclass ``cls`` written by :func:`write_record`.

    Raises:
        RecordError: the file is missing, not HDF5, of another class or version, or lacks a
            field (the message names the file).
    """
    path = Path(path)
    try:
        h5 = h5py.File(path, "r")
    except (OSError, FileNotFoundError) as exc:
        raise RecordError(f"{path}: not a readable record ({exc})") from None
    with h5:
        if int(h5.attrs.get("record_version", -1)) != RECORD_VERSION:
            raise RecordError(f"{path}: record version {h5.attrs.get('record_version')} is not "
                              f"{RECORD_VERSION}")
        if h5.attrs.get("class") != cls.__qualname__:
            raise RecordError(f"{path}: holds a {h5.attrs.get('class')}, not a "
                              f"{cls.__qualname__}")
        try:
            return _read(h5, cls, str(path))
        except (TypeError, KeyError) as exc:
            raise RecordError(f"{path}: does not match {cls.__qualname__} ({exc})") from None
