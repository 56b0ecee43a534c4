"""Settings of nested config dataclasses changed from the command line (``--set KEY=VALUE``).

``with_overrides(ProcessConfig(), ["fit.body.clothing_margin=0.005"])`` returns a copy of the
config with that one field replaced, every other setting as it was. A key is the dotted path of
field names through nested dataclasses; a nested config that is ``None`` (meaning "the stage's
default") is replaced by that class's defaults before its field is set. Values are parsed by the
field's type: ``int``, ``float``, ``bool`` (true/false/yes/no/1/0), ``str``, ``Path``, tuples of
numbers (comma-separated) and ``none`` for an optional field.
"""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

from couch.records import _strip_optional

__all__ = ["with_overrides"]

T = TypeVar("T")

_TRUE = {"true", "yes", "1", "on"}
_FALSE = {"false", "no", "0", "off"}


def _parse(tp: Any, text: str, key: str) -> Any:
    base = _strip_optional(tp)
    optional, tp = base is not tp, base
    if optional and text.strip().lower() == "none":
        return None
    try:
        if tp is bool:
            low = text.strip().lower()
            if low not in _TRUE | _FALSE:
                raise ValueError(f"not a yes/no value: {text!r}")
            return low in _TRUE
        if tp in (int, float, str):
            return tp(text)
        if tp is Path:
            return Path(text)
        if typing.get_origin(tp) is tuple:
            args = [a for a in typing.get_args(tp) if a is not Ellipsis] or [float]
            parts = [p for p in text.split(",") if p.strip()]
            kinds = args if len(args) == len(parts) else [args[0]] * len(parts)
            return tuple(k(p) for k, p in zip(kinds, parts, strict=True))
    except ValueError as exc:
        raise ValueError(f"--set {key}={text}: {exc}") from None
    raise ValueError(f"--set {key}: a field of type {tp} cannot be set from the command line")


def _replace(obj: Any, path: list[str], text: str, key: str) -> Any:
    names = {f.name for f in dataclasses.fields(obj) if f.init}
    name = path[0]
    if name not in names:
        raise ValueError(f"--set {key}: {type(obj).__name__} has no setting {name!r} (it has "
                         f"{', '.join(sorted(names))})")
    tp = typing.get_type_hints(type(obj))[name]
    if len(path) == 1:
        if dataclasses.is_dataclass(_strip_optional(tp)):
            raise ValueError(f"--set {key}: {name} is a group of settings; name one of them "
                             f"({key}.<setting>)")
        value = _parse(tp, text, key)
        try:  # the config's own checks (e.g. thresholds in order) see the new value
            return dataclasses.replace(obj, **{name: value})
        except ValueError as exc:
            raise ValueError(f"--set {key}={text}: {exc}") from None
    cls = _strip_optional(tp)
    if not dataclasses.is_dataclass(cls):
        raise ValueError(f"--set {key}: {name} is not a group of settings")
    inner = getattr(obj, name)
    if inner is None:
        inner = cls()
    return dataclasses.replace(obj, **{name: _replace(inner, path[1:], text, key)})


def with_overrides(config: T, overrides: Sequence[str]) -> T:
    """A copy of dataclass ``config`` with each ``"dotted.key=value"`` of ``overrides`` set, in
    order. Raises ValueError naming the key (and the settings there are) for an unknown key, a
    group named instead of a setting, a missing ``=`` or a value of the wrong type."""
    for item in overrides:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--set {item!r}: expected KEY=VALUE, e.g. "
                             f"fit.body.clothing_margin=0.005")
        config = _replace(config, key.split("."), text.strip(), key)
    return config
