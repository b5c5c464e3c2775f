"""Reading a scene file: bytes to a validated Config, or one message that points into the file.

Every message names the file, the dotted field, the YAML line where it can
and what is allowed (docs/contract.md, "Config"); `ConfigError` carries it
to the command line, which exits with 2. The reading is bounded whatever
the file holds:

* size: at most MAX_CONFIG_BYTES (256 KiB; the example scene is 3 KiB, a
  1000-vertex polygon about 25 KiB): about a second to read;
* text: UTF-8 (a byte-order mark is allowed), no control characters, one
  YAML document whose top level is a mapping;
* shape: at most MAX_DEPTH levels of nesting and MAX_NODES values once every
  alias is expanded, no alias that contains itself — so an alias bomb
  ("billion laughs") is refused before anything walks it;
* then the section models (`sections`), the cross-field checks (`checks`)
  and the element budget (`budget`), in that order; the first that fails
  gives the message (with the count of further problems of the same pass).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import yaml
from pydantic import ValidationError

from scissor_cli.config.body_checks import body_problems
from scissor_cli.config.body_section import section_problems
from scissor_cli.config.body_sections import BODY_SHAPES, BodyConfig
from scissor_cli.config.checks import scene_problems
from scissor_cli.config.controller_class import controller_problems, with_class_folder
from scissor_cli.config.element_budget import budget_problems
from scissor_cli.config.messages import loc_text, located, pydantic_problem, show
from scissor_cli.config.sections import Config

#: the largest scene file read, in bytes
MAX_CONFIG_BYTES = 256 * 1024
#: the deepest nesting of mappings and lists (a scene needs 5: robot.dh[0].limits[1])
MAX_DEPTH = 32
#: the most YAML values (mappings, lists, scalars, keys) with every alias expanded
MAX_NODES = 200_000


class ConfigError(Exception):
    """A bad config: the message names the file, field, YAML line and what is allowed."""


class _Constructor(yaml.constructor.SafeConstructor):
    """PyYAML's safe constructor whose scalar conversions fail as YAML errors with a line."""

    def construct_object(self, node, deep=False):
        try:
            return super().construct_object(node, deep)
        except (ValueError, OverflowError) as exc:  # a 5000-digit integer, an impossible date (February 30th)
            raise yaml.constructor.ConstructorError(
                None, None, f"cannot read the value {show(node.value)}: {exc}", node.start_mark
            ) from None


try:  # libyaml scans and parses in C, five times faster than PyYAML's own reader
    from yaml._yaml import CParser as _CParser
except ImportError:  # pragma: no cover - PyYAML built without libyaml
    _CParser = None

if _CParser is not None:

    class _Loader(yaml.composer.Composer, _CParser, _Constructor, yaml.resolver.Resolver):
        """libyaml's events, composed in Python: a deep file meets Python's recursion limit, not the C stack."""

        def __init__(self, stream):
            _CParser.__init__(self, stream)
            _Constructor.__init__(self)
            yaml.resolver.Resolver.__init__(self)
            yaml.composer.Composer.__init__(self)

else:  # pragma: no cover

    class _Loader(yaml.reader.Reader, yaml.scanner.Scanner, yaml.parser.Parser, yaml.composer.Composer,
                  _Constructor, yaml.resolver.Resolver):
        def __init__(self, stream):
            yaml.reader.Reader.__init__(self, stream)
            yaml.scanner.Scanner.__init__(self)
            yaml.parser.Parser.__init__(self)
            yaml.composer.Composer.__init__(self)
            _Constructor.__init__(self)
            yaml.resolver.Resolver.__init__(self)


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def _shape_problem(root: yaml.Node) -> Optional[tuple[yaml.Node, str]]:
    """The first node that makes the document too deep, too large or recursive, and why."""
    size: dict[int, int] = {}
    on_path: set[int] = set()
    stack: list[tuple[yaml.Node, int, bool]] = [(root, 1, False)]
    while stack:
        node, depth, finished = stack.pop()
        if finished:
            on_path.discard(id(node))
            size[id(node)] = 1 + sum(size[id(c)] for c in _children(node))
            if size[id(node)] > MAX_NODES:
                return node, (f"more than {MAX_NODES} values once its aliases are expanded (an alias bomb?); "
                              f"a scene has a few hundred")
            continue
        if id(node) in size:
            continue
        if id(node) in on_path:
            return node, "an alias refers to a block that contains it (a recursive structure)"
        if depth > MAX_DEPTH:
            return node, f"nested more than {MAX_DEPTH} levels deep; a scene nests at most 5"
        on_path.add(id(node))
        stack.append((node, depth, True))
        stack += [(c, depth + 1, False) for c in _children(node)]
    return None


_OPENS = (yaml.FlowSequenceStartToken, yaml.FlowMappingStartToken, yaml.BlockSequenceStartToken,
          yaml.BlockMappingStartToken)
_CLOSES = (yaml.FlowSequenceEndToken, yaml.FlowMappingEndToken, yaml.BlockEndToken)


def _nesting_line(text: str) -> Optional[int]:
    """The line (1-based) where the text first nests deeper than MAX_DEPTH, else None.

    Read from the pure-Python scanner's tokens, which need no recursion, so a
    parser that gave up on the depth (libyaml has its own limit, worded its
    own way) still gets our message. Stops at the first level too deep.
    """
    depth = 0
    try:
        for token in yaml.scan(text, Loader=yaml.SafeLoader):
            if isinstance(token, _OPENS):
                depth += 1
                if depth > MAX_DEPTH:
                    return token.start_mark.line + 1
            elif isinstance(token, _CLOSES):
                depth -= 1
    # not valid YAML for another reason: the parser's message stands
    except (yaml.YAMLError, ValueError, OverflowError):
        return None
    return None


def _duplicate_key(root: yaml.Node) -> Optional[tuple[tuple, yaml.Node]]:
    """(path, key node) of the first key given twice in one mapping, if any."""
    seen_nodes: set[int] = set()
    stack: list[tuple[yaml.Node, tuple]] = [(root, ())]
    while stack:
        node, path = stack.pop()
        if id(node) in seen_nodes:
            continue
        seen_nodes.add(id(node))
        if isinstance(node, yaml.MappingNode):
            keys: set[str] = set()
            for k, v in node.value:
                if isinstance(k, yaml.ScalarNode):
                    if k.value in keys:
                        return path + (k.value,), k
                    keys.add(k.value)
                stack.append((v, path + (k.value if isinstance(k, yaml.ScalarNode) else "?",)))
        elif isinstance(node, yaml.SequenceNode):
            stack += [(v, path + (i,)) for i, v in enumerate(node.value)]
    return None


def _yaml_message(source: str, text: str, exc: yaml.YAMLError) -> str:
    if isinstance(exc, yaml.reader.ReaderError):  # a character YAML does not allow, e.g. NUL
        # libyaml counts bytes
        before = text.encode("utf-8")[: exc.position] if _CParser is not None else text[: exc.position]
        line = before.count(b"\n" if isinstance(before, bytes) else "\n") + 1
        return (f"{source} (line {line}): not valid YAML: the character {exc.character:#06x} is not allowed "
                f"(control characters other than tab and newline are not YAML text)")
    mark = getattr(exc, "problem_mark", None)
    line = f" (line {mark.line + 1})" if mark is not None else ""
    problem = getattr(exc, "problem", None) or str(exc)
    context = getattr(exc, "context", None)
    return f"{source}{line}: not valid YAML: {f'{context}, ' if context else ''}{problem}"


def _read_yaml(text: str, source: str) -> tuple[yaml.Node, dict]:
    """The document's root node and its data, or ConfigError."""
    loader = None
    try:
        loader = _Loader(text)
        root = loader.get_single_node()
        if root is None:
            raise ConfigError(f"{source}: the file holds no YAML document (it is empty or only comments); "
                              f"a scene is a mapping of sections such as tissue, material, cups, targets")
        shape = _shape_problem(root)
        if shape is not None:
            node, why = shape
            raise ConfigError(f"{source} (line {node.start_mark.line + 1}): {why}")
        data = loader.construct_document(root)
    except (yaml.YAMLError, RecursionError) as exc:
        deep = _nesting_line(text)
        if deep is not None:  # the parser's own depth limit, in whichever words it has
            raise ConfigError(f"{source} (line {deep}): nested more than {MAX_DEPTH} levels deep; "
                              f"a scene nests at most 5") from None
        if isinstance(exc, RecursionError):
            raise ConfigError(f"{source}: not valid YAML: nested too deeply "
                              f"(a scene nests at most {MAX_DEPTH} levels)") from None
        raise ConfigError(_yaml_message(source, text, exc)) from None
    except (ValueError, OverflowError) as exc:  # a lone surrogate in the text; PyYAML's scanner on "\UFFFFFFFF"
        raise ConfigError(f"{source}: not valid YAML: {exc}") from None
    finally:
        if loader is not None and hasattr(loader, "dispose"):
            loader.dispose()
    if not isinstance(data, dict):
        raise ConfigError(f"{source} (line {root.start_mark.line + 1}): the top level must be a mapping of sections "
                          f"(tissue: ..., material: ..., cups: ...); got {type(data).__name__} {show(data)}")
    return root, data


def _one_message(messages: list[str]) -> str:
    extra = f"\n  (and {len(messages) - 1} more problem(s))" if len(messages) > 1 else ""
    return messages[0] + extra


def parse_config(text: str, source: str = "<config>", base_dir: Path | None = None) -> Config | BodyConfig:
    """Validate YAML text into a Config (a 2-D layer) or a BodyConfig (a 3-D body, by its tissue.shape), or raise
    ConfigError with one clear message.

    Relative paths in it (`tissue.mesh.file`) are taken from `base_dir` (the
    config file's folder; the working directory when None) and stored absolute,
    so the resolved config a run keeps finds them from anywhere.
    """
    if len(text.encode("utf-8", "surrogatepass")) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{source}: larger than {MAX_CONFIG_BYTES // 1024} KiB, the most a scene file may be")
    root, data = _read_yaml(text, source)
    dup = _duplicate_key(root)
    if dup is not None:
        loc, node = dup
        raise ConfigError(f"{source}: {loc_text(loc)} (line {node.start_mark.line + 1}): key given twice")
    body = _is_body(data)
    model, other = (BodyConfig, Config) if body else (Config, BodyConfig)
    try:
        cfg = model.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        raise ConfigError(_one_message([located(source, root, *pydantic_problem(e, model, other))
                                        for e in errors])) from None
    cfg = _absolute_paths(cfg, base_dir)
    cfg = cfg.model_copy(update={"controller": with_class_folder(cfg.controller, base_dir)})
    checks = (body_problems, section_problems) if body else (scene_problems, budget_problems)
    for check in checks + (lambda c: controller_problems(c.controller),):
        problems = check(cfg)
        if problems:
            raise ConfigError(_one_message([located(source, root, loc, what) for loc, what in problems]))
    return cfg


def _is_body(data: dict) -> bool:
    """Whether a scene's data is a 3-D scene's: its tissue's shape is a body's."""
    tissue = data.get("tissue")
    return isinstance(tissue, dict) and tissue.get("shape") in BODY_SHAPES


def _absolute_paths(cfg, base_dir: Path | None):
    where = Path(base_dir) if base_dir is not None else Path.cwd()
    if isinstance(cfg, BodyConfig):
        tissue = cfg.tissue
        update = {}
        if tissue.surface_file is not None and not Path(tissue.surface_file).is_absolute():
            update["surface_file"] = str((where / tissue.surface_file).absolute())
        if tissue.mesh.file is not None and not Path(tissue.mesh.file).is_absolute():
            update["mesh"] = tissue.mesh.model_copy(update={"file": str((where / tissue.mesh.file).absolute())})
        return cfg.model_copy(update={"tissue": tissue.model_copy(update=update)}) if update else cfg
    mesh = cfg.tissue.mesh
    if mesh.file is None or Path(mesh.file).is_absolute():
        return cfg
    mesh = mesh.model_copy(update={"file": str((where / mesh.file).absolute())})
    return cfg.model_copy(update={"tissue": cfg.tissue.model_copy(update={"mesh": mesh})})


def read_config_text(path: Path) -> str:
    """A scene file's text: at most MAX_CONFIG_BYTES of UTF-8, or ConfigError."""
    try:
        with open(path, "rb") as f:
            data = f.read(MAX_CONFIG_BYTES + 1)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the config file: {exc.strerror or exc}") from None
    if len(data) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{path}: larger than {MAX_CONFIG_BYTES // 1024} KiB, the most a scene file may be "
                          f"(the example scene is 3 KiB)")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ConfigError(f"{path} (line {line}): not UTF-8 text: byte 0x{data[exc.start]:02x} at offset {exc.start} "
                          f"cannot be decoded; a scene file is UTF-8 YAML") from None


def load_config(path: Path | str) -> Config:
    """Read and validate a YAML scene file (ConfigError on any problem)."""
    path = Path(path)
    return parse_config(read_config_text(path), str(path), base_dir=path.parent)


def resolved_yaml(cfg: Config) -> str:
    """The config with every default filled in, as YAML text."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False, default_flow_style=None, width=1000)
