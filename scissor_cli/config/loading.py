"""Reading a scene file: YAML to a validated Config, or one message that points into the file.

Every message names the file, the dotted field, the YAML line where it can
and what is allowed (docs/contract.md, "Config"); `ConfigError` carries it
to the command line, which exits with 2.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import yaml
from pydantic import BaseModel, ValidationError

from scissor_cli.config.checks import scene_problems
from scissor_cli.config.sections import Config

class ConfigError(Exception):
    """A bad config: the message names the file, field, YAML line and what is allowed."""


def _node_at(root: Optional[yaml.Node], loc: tuple) -> tuple[Optional[yaml.Node], bool]:
    """The YAML node at a field location and True, or its nearest ancestor and False."""
    node = root
    for key in loc:
        child = None
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if k.value == str(key):
                    child = v
                    break
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            child = node.value[key]
        if child is None:
            return node, False
        node = child
    return node, True


def _loc_text(loc: tuple) -> str:
    out = ""
    for key in loc:
        out += f"[{key}]" if isinstance(key, int) else (f".{key}" if out else str(key))
    return out or "(top level)"


def _allowed_fields(loc: tuple) -> list[str]:
    model: Any = Config
    for key in loc:
        if isinstance(key, int):
            continue
        field = model.model_fields.get(key)
        if field is None:
            return []
        ann = field.annotation
        nested = [a for a in _flatten_annotation(ann) if isinstance(a, type) and issubclass(a, BaseModel)]
        if not nested:
            return []
        model = nested[0]
    return list(model.model_fields)


def _flatten_annotation(ann) -> list:
    args = getattr(ann, "__args__", None)
    if not args:
        return [ann]
    out = []
    for a in args:
        out += _flatten_annotation(a)
    return out


def _message(source: str, root, loc: tuple, what: str) -> str:
    node, exact = _node_at(root, loc)
    where = f" (line {node.start_mark.line + 1})" if node is not None else ""
    if not exact and node is not None:
        where = f" (in the block at line {node.start_mark.line + 1})"
    return f"{source}: {_loc_text(loc)}{where}: {what}"


def _pydantic_message(err: dict) -> tuple[tuple, str]:
    loc = tuple(err["loc"])
    kind = err["type"]
    if kind == "extra_forbidden":
        allowed = _allowed_fields(loc[:-1])
        return loc, f"unknown key {loc[-1]!r}; allowed keys: {', '.join(allowed)}"
    if kind == "missing":
        return loc, "required field is missing"
    got = err.get("input")
    if kind.endswith("_type") or kind in ("literal_error", "too_short", "too_long"):
        return loc, f"{err['msg']}; got {got!r}"
    return loc, f"{err['msg']}; got {got!r}"


def _duplicate_keys(node, path=()) -> list[tuple[tuple, yaml.Node]]:
    out = []
    if isinstance(node, yaml.MappingNode):
        seen = set()
        for k, v in node.value:
            if k.value in seen:
                out.append((path + (k.value,), k))
            seen.add(k.value)
            out += _duplicate_keys(v, path + (k.value,))
    elif isinstance(node, yaml.SequenceNode):
        for i, v in enumerate(node.value):
            out += _duplicate_keys(v, path + (i,))
    return out


def parse_config(text: str, source: str = "<config>") -> Config:
    """Validate YAML text into a Config, or raise ConfigError with one clear message."""
    try:
        root = yaml.compose(text)
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" (line {mark.line + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(f"{source}{line}: not valid YAML: {problem}") from None
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: the top level must be a mapping of sections, got {type(data).__name__}")
    dups = _duplicate_keys(root)
    if dups:
        loc, node = dups[0]
        raise ConfigError(f"{source}: {_loc_text(loc)} (line {node.start_mark.line + 1}): key given twice")
    try:
        cfg = Config.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        msgs = [_message(source, root, *_pydantic_message(e)) for e in errors]
        extra = f"\n  (and {len(msgs) - 1} more problem(s))" if len(msgs) > 1 else ""
        raise ConfigError(msgs[0] + extra) from None
    problems = scene_problems(cfg)
    if problems:
        msgs = [_message(source, root, loc, what) for loc, what in problems]
        extra = f"\n  (and {len(msgs) - 1} more problem(s))" if len(msgs) > 1 else ""
        raise ConfigError(msgs[0] + extra)
    return cfg


def load_config(path: Path | str) -> Config:
    """Read and validate a YAML scene file (ConfigError on any problem)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the config file: {exc.strerror or exc}") from None
    return parse_config(text, str(path))


def resolved_yaml(cfg: Config) -> str:
    """The config with every default filled in, as YAML text."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False, default_flow_style=None, width=1000)
