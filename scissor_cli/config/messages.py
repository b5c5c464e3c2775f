"""Messages about a scene file: where a problem is (dotted field, YAML line) and what is allowed.

Every message has the form `FILE: FIELD (line N): WHAT; got VALUE`
(docs/contract.md, "Config"). The field is the dotted path with list
indices in brackets (`targets[0].position_mm`); the line is that of the
field's YAML node, or of the nearest enclosing block when the field is
missing. What is allowed comes from the section models themselves: the
range of a number, the pattern of a name, the keys of a section.
"""

from __future__ import annotations

import re
import typing
from typing import Any, Optional

import yaml
from pydantic import BaseModel

from scissor_cli.config.sections import CLASS_PATH, NAME_PATTERN, SCENE_NAME_PATTERN, Config

#: values and keys are shown at most this long in a message
SHOW_CHARS = 60

_PLAIN_KEY = re.compile(r"^[A-Za-z0-9_.+-]{1,64}$")


def show(value: Any) -> str:
    """A value as a message shows it: repr (escapes control characters), cut to SHOW_CHARS."""
    text = repr(value)
    return text if len(text) <= SHOW_CHARS else text[: SHOW_CHARS - 4] + " ..."


def loc_text(loc: tuple) -> str:
    """('targets', 0, 'position_mm') -> 'targets[0].position_mm'; odd keys are quoted."""
    out = ""
    for key in loc:
        if isinstance(key, int):
            out += f"[{key}]"
            continue
        key = str(key) if isinstance(key, str) and _PLAIN_KEY.match(key) else show(key)
        out += f".{key}" if out else key
    return out or "(top level)"


def node_at(root: Optional[yaml.Node], loc: tuple) -> tuple[Optional[yaml.Node], bool]:
    """The YAML node at a field location and True, or its nearest ancestor and False."""
    node = root
    for key in loc:
        child = None
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode) and k.value == str(key):
                    child = v
                    break
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and 0 <= key < len(node.value):
            child = node.value[key]
        if child is None:
            return node, False
        node = child
    return node, True


def located(source: str, root: Optional[yaml.Node], loc: tuple, what: str) -> str:
    """The full message: file, field, line, what is wrong."""
    node, exact = node_at(root, loc)
    where = ""
    if node is not None:
        line = node.start_mark.line + 1
        where = f" (line {line})" if exact else f" (in the block at line {line})"
    return f"{source}: {loc_text(loc)}{where}: {what}"


# --------------------------------------------------------------------------
# What a field allows, read from the section models


def _unwrap(tp: Any) -> tuple[Any, list]:
    """(bare type, constraint metadata) of an annotation: Annotated and Optional peeled off."""
    meta: list = []
    while True:
        origin = typing.get_origin(tp)
        if origin is typing.Annotated:
            tp, *extra = typing.get_args(tp)
            for m in extra:
                meta += list(getattr(m, "metadata", [])) if hasattr(m, "metadata") else [m]
            continue
        if origin is typing.Union:
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp, meta


def field_type(loc: tuple, root: type = Config) -> tuple[Any, list]:
    """The (type, constraints) a location in a config model (`Config`, or a 3-D scene's) holds, or (None, [])."""
    tp: Any = root
    meta: list = []
    for key in loc:
        tp, _ = _unwrap(tp)
        origin = typing.get_origin(tp)
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            field = tp.model_fields.get(key) if isinstance(key, str) else None
            if field is None:
                return None, []
            tp, meta = field.annotation, list(field.metadata)
        elif origin is list and isinstance(key, int):
            tp, meta = typing.get_args(tp)[0], []
        elif origin is dict and isinstance(key, str):
            tp, meta = typing.get_args(tp)[1], []
        else:
            return None, []
    bare, inner = _unwrap(tp)
    return bare, meta + inner


def allowed_keys(loc: tuple, root: type = Config) -> list[str]:
    """The keys the section at loc allows (empty if loc is not a section)."""
    tp, _ = field_type(loc, root)
    return list(tp.model_fields) if isinstance(tp, type) and issubclass(tp, BaseModel) else []


def _bounds(meta: list) -> str:
    lo = hi = None
    lo_open = hi_open = False
    for m in meta:
        if getattr(m, "ge", None) is not None:
            lo = m.ge
        if getattr(m, "gt", None) is not None:
            lo, lo_open = m.gt, True
        if getattr(m, "le", None) is not None:
            hi = m.le
        if getattr(m, "lt", None) is not None:
            hi, hi_open = m.lt, True
    if lo is None and hi is None:
        return ""
    left = "(" if lo_open else "["
    right = ")" if hi_open else "]"
    lo_text, hi_text = (str(v) if isinstance(v, int) else f"{v:g}" for v in (lo, hi))
    return f" in {left}{lo_text}, {hi_text}{right}" if lo is not None and hi is not None else (
        f" {'>' if lo_open else '>='} {lo_text}" if lo is not None else f" {'<' if hi_open else '<='} {hi_text}")


def allowed(loc: tuple, root: type = Config) -> str:
    """What the field at loc allows, in words ('' when the model says nothing more)."""
    tp, meta = field_type(loc, root)
    if tp is float:
        return "a finite number" + _bounds(meta)
    if tp is int:
        return "an integer" + _bounds(meta)
    if tp is bool:
        return "true or false"
    if tp is str:
        patterns = [getattr(m, "pattern", None) for m in meta]
        if NAME_PATTERN in patterns:
            return "a name of 1 to 64 letters, digits, '_', '.', '+' or '-', starting with a letter or digit"
        if SCENE_NAME_PATTERN in patterns:
            return "a name of 1 to 128 letters, digits, spaces, '_', '.', '+' or '-', starting with a letter or digit"
        if CLASS_PATH in patterns:
            return "a class as \"package.module:Class\" (dotted Python names, a colon, the class's name)"
        return "a string"
    if typing.get_origin(tp) is typing.Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(tp))
    if typing.get_origin(tp) is list:
        lengths = [m for m in meta if hasattr(m, "min_length")]
        n = ""
        if lengths:
            lo, hi = lengths[0].min_length, lengths[0].max_length
            n = f" of {lo}" if lo == hi else (f" of {lo} to {hi}" if hi is not None else f" of at least {lo}")
        return f"a list{n} items"
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return "a mapping with keys " + ", ".join(tp.model_fields)
    return ""


def pydantic_problem(err: dict, root: type = Config, other: type | None = None) -> tuple[tuple, str]:
    """(location, what) of one pydantic error of a `root` model, with what the field allows.

    other: the model of the other dimension (2-D layer or 3-D body): an
    unknown key that is one of its fields is named as such.
    """
    loc = tuple(err["loc"])
    kind = err["type"]
    if kind == "extra_forbidden":
        what = f"unknown key {show(loc[-1])}; allowed keys: {', '.join(allowed_keys(loc[:-1], root))}"
        if other is not None and isinstance(loc[-1], str) and field_type(loc, other)[0] is not None:
            kinds = ("a 3-D scene's (tissue.shape dome | surface)" if root is Config
                     else "a 2-D layer's (tissue.shape rectangle | ellipse | polygon)")
            what = f"{show(loc[-1])} is {kinds} field, not this scene's; {what}"
        return loc, what
    if kind == "missing":
        return loc, "required field is missing" + (f"; allowed: {allowed(loc, root)}" if allowed(loc, root) else "")
    what = err["msg"]
    allow = allowed(loc, root)
    got = err.get("input")
    if allow and kind not in ("value_error", "assertion_error"):
        what = f"must be {allow}"  # says more than pydantic's words: the whole range, the name's characters
    if allow.startswith(("a finite number", "an integer")) and isinstance(got, str) and _number_like(got):
        what += f" (YAML read {got} as text: write exponents with a sign, 1.0e+3, and no quotes)"
    return loc, f"{what}; got {show(got)}"


def _number_like(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True
