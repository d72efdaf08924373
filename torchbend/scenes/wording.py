"""The wording of config errors: :class:`ConfigError` (a ``ValueError`` whose one-line message names the
key's dotted path), the quoting of a user's values (:func:`short_repr`, :func:`one_line`) and the
translation of pydantic's validation errors into those messages (:func:`describe`)."""
from __future__ import annotations

import re
import reprlib
import types
from collections.abc import Mapping
from typing import Annotated, Any, TypeGuard, Union, get_args, get_origin

from .._extras import missing_extra

try:
    from pydantic import BaseModel, Tag
except ModuleNotFoundError as _err:
    raise missing_extra(_err, "torchbend.scenes (configs)") from None

__all__ = ["ConfigError", "short_repr", "one_line", "describe", "QUOTE_LIMIT", "MESSAGE_LIMIT", "MAX_ERRORS"]

QUOTE_LIMIT = 200
"""The most characters of an offending value (or of any one quoted run or word) a message shows."""
MESSAGE_LIMIT = 1000
"""The most characters of a whole error message (longer ones keep their start and end)."""
MAX_ERRORS = 5
"""The most validation errors one :class:`ConfigError` lists (then ``... and N more``)."""

_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = QUOTE_LIMIT
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 8
_REPR.maxlevel = 4


def _clip(text: str, limit: int) -> str:
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text)} characters)"


def short_repr(value: Any, limit: int = QUOTE_LIMIT) -> str:
    """``repr(value)`` in at most about ``limit`` characters (long strings and deep or long
    containers elided with ``...``), for quoting a user's value in an error message."""
    try:
        text = _REPR.repr(value)
    except Exception:  # a value whose repr fails is quoted by its type
        text = f"<{type(value).__name__}>"
    return _clip(text, limit)


# a quoted run (the closing quote kept) or a word, longer than QUOTE_LIMIT
_LONG = re.compile("('[^'\n]{N,})'|(\"[^\"\n]{N,})\"|(\\S{N,})".replace("N", str(QUOTE_LIMIT)))


def _clip_match(m: re.Match) -> str:
    if m.group(3) is not None:
        return _clip(m.group(3), QUOTE_LIMIT)
    quoted = m.group(1) if m.group(1) is not None else m.group(2)
    return _clip(quoted, QUOTE_LIMIT) + quoted[0]


def one_line(message: Any, limit: int = MESSAGE_LIMIT) -> str:
    """``message`` as one line of at most about ``limit`` characters: line breaks become spaces, a
    quoted run or a word longer than :data:`QUOTE_LIMIT` keeps its first :data:`QUOTE_LIMIT`
    characters (then ``... (N characters)``), an overlong whole keeps its start and end."""
    text = re.sub(r"\s*[\r\n]+\s*", " ", str(message)).strip()
    text = _LONG.sub(_clip_match, text)
    if len(text) > limit:
        text = f"{text[:limit * 3 // 4]} ... {text[-(limit // 4):]}"
    return text


class ConfigError(ValueError):
    """A config problem: the message names the key's dotted path (``solver.tol``, ``colliders[0].radius``).

    The message is kept to one line and quotes at most about :data:`QUOTE_LIMIT` characters of any
    value (:func:`one_line`)."""

    def __init__(self, message: Any = ""):
        super().__init__(one_line(message))



# ------------------------------------------------------------------------------ errors
def _strip(tp):
    """``tp`` without ``Annotated`` and ``Optional``."""
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            tp = get_args(tp)[0]
        elif origin in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return tp
            tp = args[0]
        else:
            return tp


def _is_model(tp) -> TypeGuard[type[BaseModel]]:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _walk(schema, loc, prefix: str = ""):
    """``(dotted path, type at the end)`` of a pydantic error location; drops the tags that
    discriminated unions put into locations (``colliders.0.sphere.radius`` -> ``colliders[0].radius``)."""
    path, tp = prefix, schema
    for part in loc:
        tp = _strip(tp) if tp is not None else None
        if get_origin(tp) in (Union, types.UnionType) and isinstance(part, str):
            members = [m for m in get_args(tp) if _is_model(m) and "type" in m.model_fields
                       and part in get_args(m.model_fields["type"].annotation)]
            if members:
                tp = members[0]
                continue
            tagged = [m for m in get_args(tp) if get_origin(m) is Annotated
                      and any(isinstance(meta, Tag) and meta.tag == part for meta in m.__metadata__)]
            if tagged:  # a union discriminated by a function (``mesh.pin``): the tag is no key either
                tp = tagged[0]
                continue
        if isinstance(part, int):
            path += f"[{part}]"
            args = get_args(tp) if get_origin(tp) in (list, tuple) else ()
            tp = args[0] if args else None
        else:
            path += f".{part}" if path else str(part)
            field = tp.model_fields.get(part) if _is_model(tp) else None
            tp = field.annotation if field is not None else None
    return path, tp


_SIMPLE = {
    **dict.fromkeys(("model_type", "model_attributes_type", "dict_type"), "must be a mapping"),
    **dict.fromkeys(("list_type", "tuple_type"), "must be a list"),
    **dict.fromkeys(("float_parsing", "float_type", "finite_number"), "must be a finite number"),
    **dict.fromkeys(("int_parsing", "int_type", "int_from_float"), "must be an integer"),
    **dict.fromkeys(("bool_parsing", "bool_type"), "must be true or false"),
    "string_type": "must be a string",
}
"""Error kinds whose message is ``config key 'path' <words>, got <value>``."""
_BOUNDS = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
_BOUND_WORDS = {("greater_than", 0): "positive", ("greater_than_equal", 0): "non-negative"}


def describe(error: Mapping[str, Any], schema, prefix: str) -> str:
    """One pydantic validation error in words, naming the key's dotted path (below ``prefix``)."""
    kind, loc, ctx = error["type"], error["loc"], error.get("ctx") or {}
    value = error.get("input")
    path, _ = _walk(schema, loc, prefix)
    key = f"config key '{path}'" if path else "the config"
    if kind == "extra_forbidden":
        _, parent = _walk(schema, loc[:-1], prefix)
        parent = _strip(parent)
        allowed = f" (allowed: {', '.join(parent.model_fields)})" if _is_model(parent) else ""
        return f"unknown config key '{path}'{allowed}"
    if kind == "missing":
        return f"missing config key '{path}'"
    if kind in _SIMPLE:
        return f"{key} {_SIMPLE[kind]}, got {short_repr(value)}"
    if kind in _BOUNDS:
        bound = next(iter(ctx.values()))
        return f"{key} must be {_BOUND_WORDS.get((kind, bound)) or f'{_BOUNDS[kind]} {bound}'}, got {short_repr(value)}"
    return _describe_other(kind, key, ctx, value, error)


def _describe_other(kind: str, key: str, ctx: Mapping[str, Any], value, error: Mapping[str, Any]) -> str:
    if kind == "union_tag_invalid":
        disc = ctx["discriminator"].strip("'")
        return f"{key[:-1]}.{disc}' must be one of {ctx['expected_tags']}, got {short_repr(ctx['tag'])}"
    if kind == "union_tag_not_found":
        return f"{key} needs a {ctx['discriminator']} key, got {short_repr(value)}"
    if kind == "literal_error":
        return f"{key} must be one of {ctx['expected'].replace(' or ', ', ')}, got {short_repr(value)}"
    if kind == "value_error":
        msg = str(ctx.get("error", error["msg"]))
        return f"{key} {msg}" if msg.startswith("must ") else f"{key}: {msg}"
    return f"{key}: {error['msg']}, got {short_repr(value)}"
