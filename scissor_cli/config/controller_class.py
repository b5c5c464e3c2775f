"""A `controller.law: python` class: found from its `class_path` and checked against its `init_args`
(docs/model.md §22).

The class is imported from `controller.class_folder` (the config file's
folder unless given), so a controller beside the scene file needs no
install. The folder is put first on `sys.path` for the import only (a
module of that name the process has already imported is used as it is).
What can go wrong is the config's problem (exit 2, naming the
field): a module that does not import, a missing class, a class without
`act`, `init_args` its constructor does not take.
"""

from __future__ import annotations

import importlib
import inspect
import sys
from pathlib import Path
from typing import Optional

from scissor_cli.config.sections import ControllerConfig

Problem = tuple[tuple, str]


class ControllerClassError(ValueError):
    """The class cannot be had: (field, what) names the config field and why."""

    def __init__(self, field: str, what: str):
        super().__init__(what)
        self.field, self.what = field, what


def controller_class(class_path: str, folder: Optional[str]) -> type:
    """The class `class_path` ("package.module:Class") names, imported with `folder` first on the path."""
    module_name, _, class_name = class_path.partition(":")
    added = folder is not None and folder not in sys.path
    if added:
        sys.path.insert(0, folder)
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # noqa: BLE001 - whatever the user's module raises on import is their config's problem
        where = f" (searched {folder} first)" if folder else ""
        raise ControllerClassError("class_path", f"cannot import {module_name!r}{where}: "
                                                 f"{type(exc).__name__}: {exc}") from None
    finally:
        if added:
            sys.path.remove(folder)
    cls = getattr(module, class_name, None)
    if not inspect.isclass(cls):
        raise ControllerClassError("class_path", f"module {module_name!r} has no class {class_name!r}")
    missing = [m for m in ("reset", "act") if not callable(getattr(cls, m, None))]
    if missing:
        raise ControllerClassError("class_path", f"class {class_path!r} has no method {' or '.join(missing)}; a "
                                                 "controller has reset(observation, info) and act(observation, info)")
    return cls


def controller_instance(controller: ControllerConfig):
    """A new instance of the configured class with its `init_args` (ControllerClassError naming the field)."""
    cls = controller_class(controller.class_path, controller.class_folder)
    _check_arguments(cls, controller)
    try:
        return cls(**controller.init_args)
    except Exception as exc:  # noqa: BLE001 - the user's constructor may raise anything
        raise ControllerClassError("init_args", f"{controller.class_path}({_args_text(controller)}) raised "
                                                f"{type(exc).__name__}: {exc}") from None


def _check_arguments(cls: type, controller: ControllerConfig) -> None:
    try:
        inspect.signature(cls).bind(**controller.init_args)
    except TypeError as exc:
        raise ControllerClassError("init_args", f"{controller.class_path} does not take "
                                                f"({_args_text(controller)}): {exc}") from None
    except ValueError:  # no signature to read (a builtin): the constructor call will say
        pass


def _args_text(controller: ControllerConfig) -> str:
    return ", ".join(f"{k}={v!r}" for k, v in controller.init_args.items())


def with_class_folder(controller: ControllerConfig, base_dir: Optional[Path]) -> ControllerConfig:
    """The section with `class_folder` absolute (relative to `base_dir`, the config's folder; default it)."""
    if controller.law != "python":
        return controller
    where = Path(base_dir) if base_dir is not None else Path.cwd()
    folder = where if controller.class_folder is None else where / controller.class_folder
    return controller.model_copy(update={"class_folder": str(folder.absolute())})


def controller_problems(controller: ControllerConfig) -> list[Problem]:
    """The `controller` fields' problems with the law they choose (the class imported, its arguments bound)."""
    law = controller.law
    if law != "python":
        extra = [f for f in ("class_path", "class_folder") if getattr(controller, f) is not None]
        extra += ["init_args"] if controller.init_args else []
        return [(("controller", f), f"only used with law 'python' (law is {law!r}): remove it") for f in extra]
    if controller.class_path is None:
        return [(("controller", "class_path"), "law 'python' needs the controller class, "
                                               "\"package.module:Class\" (importable from the config's folder)")]
    if not Path(controller.class_folder).is_dir():
        return [(("controller", "class_folder"), f"{controller.class_folder} is not a folder")]
    try:
        _check_arguments(controller_class(controller.class_path, controller.class_folder), controller)
    except ControllerClassError as exc:
        return [(("controller", exc.field), exc.what)]
    return []
