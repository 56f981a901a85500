"""The generated part of ``docs/protocol.md``: Markdown tables of every bus message, from the classes themselves.

:func:`markdown_tables` renders the type aliases and each message's fields in wire order;
:func:`update_doc` rewrites the section between :data:`DOC_BEGIN` and :data:`DOC_END`. Run as
``python -m studio.backend.protocol_doc --update docs/protocol.md`` (without arguments it prints the tables).
"""

from __future__ import annotations

import sys
import typing
from typing import Annotated, Any, Literal, Union

import msgspec

from studio.backend.messages import (
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    ArrayData,
    Count,
    GeomSpec,
    Id,
    ImageEncoding,
    JobState,
    MeshSpec,
    Name,
    Pixels,
    Quality,
    Role,
    Seed,
    Text,
    Unit,
    Vec3,
    Vec4,
)

_ALIASES = {
    "Id": Id,
    "Name": Name,
    "Text": Text,
    "Count": Count,
    "Unit": Unit,
    "Vec3": Vec3,
    "Vec4": Vec4,
    "Seed": Seed,
    "Pixels": Pixels,
    "Quality": Quality,
    "Role": Role,
    "ImageEncoding": ImageEncoding,
    "JobState": JobState,
}


def _type_name(tp: Any, use_aliases: bool = True) -> str:
    """Short, readable rendering of a field type for the documentation tables."""
    for alias, value in _ALIASES.items():
        if use_aliases and tp == value:
            return alias
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        base, *metas = args
        limits = []
        for meta in metas:
            for key in ("ge", "gt", "le", "lt", "min_length", "max_length", "pattern"):
                value = getattr(meta, key, None)
                if value is not None:
                    limits.append(f"{key}={value}")
        return f"{_type_name(base)} ({', '.join(limits)})"
    if origin is Literal:
        return " \\| ".join(repr(a) for a in args)
    if origin is Union:
        return " \\| ".join(_type_name(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"tuple[{_type_name(args[0])}, ...]"
        return f"tuple[{', '.join(_type_name(a) for a in args)}]"
    if origin is dict:
        return f"dict[{_type_name(args[0])}, {_type_name(args[1])}]"
    if tp is type(None):
        return "None"
    if tp is Any:
        return "Any"
    return getattr(tp, "__name__", repr(tp))


def _describe_alias(value: Any) -> str:
    if typing.get_origin(value) is Literal:
        return " \\| ".join(repr(a) for a in typing.get_args(value))
    return _type_name(value, use_aliases=False)


def markdown_tables() -> str:
    """Markdown tables of every message (fields in wire order), generated for ``docs/protocol.md``."""
    lines = [f"Protocol version: **{PROTOCOL_VERSION}**", "", "| type name | meaning |", "|---|---|"]
    for alias, value in _ALIASES.items():
        lines.append(f"| {alias} | {_describe_alias(value)} |")
    lines.append("")
    structs: list[type[msgspec.Struct]] = [*MESSAGE_TYPES, GeomSpec, MeshSpec, ArrayData]
    for cls in structs:
        tagged = cls in MESSAGE_TYPES
        doc = " ".join((cls.__doc__ or "").split())
        lines.append(f"### `{cls.__name__}`" + ("" if tagged else " (nested record)"))
        lines.append("")
        lines.append(doc)
        lines.append("")
        lines.append("| # | field | type | default |")
        lines.append("|---|---|---|---|")
        hints = typing.get_type_hints(cls, include_extras=True)
        start = 1 if tagged else 0
        if tagged:
            lines.append(f'| 0 | (tag) | `"{cls.__name__}"` | |')
        for i, f in enumerate(msgspec.structs.fields(cls)):
            default = "" if f.required else f"`{f.default!r}`"
            lines.append(f"| {i + start} | `{f.name}` | {_type_name(hints[f.name])} | {default} |")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


DOC_BEGIN = (
    "<!-- BEGIN GENERATED MESSAGE TABLES: python -m studio.backend.protocol_doc --update docs/protocol.md -->"
)
DOC_END = "<!-- END GENERATED MESSAGE TABLES -->"


def update_doc(path: str) -> bool:
    """Rewrite the generated section of ``path`` (between :data:`DOC_BEGIN` and :data:`DOC_END`)."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    head, sep1, rest = text.partition(DOC_BEGIN)
    _, sep2, tail = rest.partition(DOC_END)
    if not (sep1 and sep2):
        raise ValueError(f"{path} lacks the generated-section markers")
    new = f"{head}{DOC_BEGIN}\n\n{markdown_tables()}\n{DOC_END}{tail}"
    if new != text:
        with open(path, "w", encoding="utf-8") as f:
            f.write(new)
    return new != text


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--update":
        print("updated" if update_doc(sys.argv[2]) else "up to date", sys.argv[2])
    else:
        sys.stdout.write(markdown_tables())
