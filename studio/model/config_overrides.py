"""Typed ``section.field=value`` overrides: the text of one value parsed against its dataclass field's declared type.

``studio train --set train.lr_max=3e-4`` and the studio's training panel write overrides as text. Each value is
read as the type its field declares, and anything else is refused with one line naming the field, its type and
the value (``train.lr_max: expected float, got '3e-4x'``):

* ``bool``: ``true``/``false``/``1``/``0``, in any case — never a truthy string such as ``flase``;
* ``int``: an integer (``3.5`` and ``1e3`` are refused); ``float``: a finite number;
* ``str``: the text as it is, or a JSON string (``"bf16"``) without its quotes; ``Literal[...]``: one of its
  choices, written either way;
* ``tuple``/``list``: a JSON array (``[96, 128]``, ``[[0, 1], [1, 0]]``) or comma-separated items (``encoder,head``),
  each item of the element type; a fixed-length tuple (``tuple[int, int]``) needs exactly that many;
* ``X | None``: ``none``/``null`` for None, else an ``X``.

:func:`parse_overrides` maps each section to its dataclass and returns the typed changes per section;
:func:`parse_value` is the conversion of one value.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import re
import types
import typing
from typing import Any, Literal, Union

_INTEGER = re.compile(r"[+-]?\d+")
_TRUE, _FALSE = ("true", "1"), ("false", "0")


class _Mismatch(Exception):
    """A value that is not of the expected type (turned into the one-line ``ValueError`` by :func:`parse_value`)."""


def type_name(tp: Any) -> str:
    """How a declared type reads in an error message (``float``, ``one of 'joint', 'divided'``, ``tuple[int, int]``)."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin in (Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        names = " | ".join(type_name(a) for a in inner)
        return f"{names} or none" if len(inner) < len(args) else names
    if origin in (tuple, list):
        return f"{origin.__name__}[{', '.join('...' if a is Ellipsis else type_name(a) for a in args)}]"
    if tp is bool:
        return "bool (true/false/1/0)"
    return getattr(tp, "__name__", str(tp))


def _items(value: Any) -> list[Any]:
    """The items of a sequence value: a JSON list as decoded, or a text as a JSON array or comma-separated items."""
    if isinstance(value, list | tuple):
        return list(value)
    if not isinstance(value, str):
        raise _Mismatch
    text = value.strip()
    if text.startswith("["):
        try:
            decoded = json.loads(text)
        except json.JSONDecodeError:
            raise _Mismatch from None
        if not isinstance(decoded, list):
            raise _Mismatch
        return decoded
    return [part.strip() for part in text.split(",") if part.strip()]


def _unquoted(value: Any) -> Any:
    """A text written as a JSON string (``"bf16"``) without its quotes; anything else as it is."""
    if isinstance(value, str) and len(value) >= 2 and value[0] == value[-1] == '"':
        try:
            decoded = json.loads(value)
        except json.JSONDecodeError:
            return value
        return decoded if isinstance(decoded, str) else value
    return value


def _convert(value: Any, tp: Any) -> Any:
    """``value`` (a text, or what a JSON array held) as an instance of ``tp``; raises ``_Mismatch`` otherwise."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (Union, types.UnionType):
        if type(None) in args and (value is None or str(value).strip().lower() in ("none", "null")):
            return None
        for option in args:
            if option is type(None):
                continue
            try:
                return _convert(value, option)
            except _Mismatch:
                continue
        raise _Mismatch
    if origin is Literal:
        value = _unquoted(value)
        for choice in args:
            if value == choice:
                return choice
        raise _Mismatch
    if origin is tuple:
        items = _items(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(item, args[0]) for item in items)
        if len(items) != len(args):
            raise _Mismatch
        return tuple(_convert(item, arg) for item, arg in zip(items, args, strict=True))
    if origin is list:
        return [_convert(item, args[0]) for item in _items(value)]
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, int) and value in (0, 1):
            return bool(value)
        if isinstance(value, str) and value.strip().lower() in _TRUE + _FALSE:
            return value.strip().lower() in _TRUE
        raise _Mismatch
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, str) and _INTEGER.fullmatch(value.strip()):
            return int(value.strip())
        raise _Mismatch
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            number = float(value)
        elif isinstance(value, str):
            try:
                number = float(value.strip())
            except ValueError:
                raise _Mismatch from None
        else:
            raise _Mismatch
        if not math.isfinite(number):
            raise _Mismatch
        return number
    if tp is str:
        if isinstance(value, str):
            return _unquoted(value)
        raise _Mismatch
    raise TypeError(f"overrides cannot set a field of type {type_name(tp)}")


def parse_value(key: str, raw: str, tp: Any) -> Any:
    """``raw`` read as the declared type ``tp`` of the field named ``key``; ``ValueError`` saying so if it is not."""
    try:
        return _convert(raw, tp)
    except _Mismatch:
        raise ValueError(f"{key}: expected {type_name(tp)}, got {raw!r}") from None


def parse_overrides(assignments: list[str], sections: dict[str, type]) -> dict[str, dict[str, Any]]:
    """The typed changes that ``section.field=value`` ``assignments`` make to each section's dataclass (a later
    assignment of a field wins). Raises ``ValueError`` with one line for a malformed assignment, an unknown
    section or field (with the closest field name when there is one) or a value not of the field's type."""
    hints = {section: typing.get_type_hints(cls) for section, cls in sections.items()}
    fields = {section: [f.name for f in dataclasses.fields(cls)] for section, cls in sections.items()}
    changes: dict[str, dict[str, Any]] = {section: {} for section in sections}
    shape = " or ".join(f"{section}.field=value" for section in sections)
    for item in assignments:
        key, sep, raw = item.partition("=")
        section, dot, name = key.strip().partition(".")
        if not sep or not dot or section not in sections:
            raise ValueError(f"override {item!r} must look like {shape}")
        if name not in fields[section]:
            close = difflib.get_close_matches(name, fields[section], n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"known: {', '.join(sorted(fields[section]))}"
            raise ValueError(f"unknown {section} field {name!r}; {hint}")
        changes[section][name] = parse_value(f"{section}.{name}", raw, hints[section][name])
    return changes
