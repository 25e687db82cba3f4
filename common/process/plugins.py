"""The user's own extensions of a process: ``SRL_PLUGINS``.

``SRL_PLUGINS`` is a comma-separated list of Python files (``path/to/model.py``) and importable
modules (``mypackage.srl_models``). Every srl process (the ``srl`` command, ``python -m
services.<name>``, the experiment's worker processes) imports each one, in order, before it
builds its command line, and calls its
``register()``: that is where a plugin adds its rows (a plant model:
:func:`common.math.plant_models.register_plant_model`, an agent:
:func:`common.math.agents.register_agent`). The processes ``srl up`` starts inherit
the variable, so a model registered this way runs in every service. A plugin that cannot be
imported, has no ``register()``, or whose ``register()`` raises stops the process with one line
(:class:`PluginError`) before anything starts.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path
from types import ModuleType

VARIABLE = "SRL_PLUGINS"


class PluginError(RuntimeError):
    """A plugin that cannot be loaded: said in one line."""


def _import(entry: str) -> ModuleType:
    if entry.endswith(".py"):
        path = Path(entry).expanduser().resolve()
        if not path.is_file():
            raise PluginError(f"{VARIABLE}: no file {path}")
        name = f"srl_plugin_{path.stem}"
        spec = importlib.util.spec_from_file_location(name, path)
        if spec is None or spec.loader is None:
            raise PluginError(f"{VARIABLE}: cannot load {path} as Python")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module  # dataclasses and pickling look modules up by name
        spec.loader.exec_module(module)
        return module
    return importlib.import_module(entry)


def load_plugins(value: str | None) -> list[str]:
    """Import every plugin of ``value`` (``SRL_PLUGINS``'s text; None or blank: none) and call its
    ``register()``; the entries loaded. Loading the same entry twice in a process does nothing
    the second time."""
    loaded: list[str] = []
    for entry in (part.strip() for part in (value or "").split(",")):
        if not entry:
            continue
        if entry in _LOADED:
            loaded.append(entry)
            continue
        try:
            module = _import(entry)
        except PluginError:
            raise
        except Exception as error:  # any import failure of the user's code: one line, not a traceback
            raise PluginError(f"{VARIABLE}: cannot import {entry!r}: {type(error).__name__}: {error}") from None
        register = getattr(module, "register", None)
        if not callable(register):
            raise PluginError(f"{VARIABLE}: {entry!r} has no register() function")
        try:
            register()
        except Exception as error:
            raise PluginError(f"{VARIABLE}: {entry!r} register() failed: {type(error).__name__}: {error}") from None
        _LOADED.add(entry)
        loaded.append(entry)
    return loaded


def load_from_environment() -> list[str]:
    """:func:`load_plugins` of ``SRL_PLUGINS``: what every srl process does first
    (common.process.runtime.entry), and each worker process srl spawns (the experiment's: a
    spawned interpreter starts afresh and inherits the variable)."""
    import os

    return load_plugins(os.environ.get(VARIABLE))


_LOADED: set[str] = set()
