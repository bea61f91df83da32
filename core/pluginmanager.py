"""Plugin discovery with pluggy: entry-point group ``vistac``.

vistac's own entry points are always loaded. Third-party ones are loaded automatically unless
``VISTAC_DISABLE_PLUGIN_AUTOLOAD=1`` is set; ``-p NAME`` (an entry-point name or an importable
module) adds one explicitly. A plugin that fails to import or register is reported and
skipped, never fatal.
"""

from __future__ import annotations

import importlib
import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from importlib.metadata import EntryPoint, entry_points
from types import ModuleType

import pluggy
from vistac import hookspecs
from vistac.registry import Registry

log = logging.getLogger(__name__)

ENTRY_POINT_GROUP = "vistac"
AUTOLOAD_ENV = "VISTAC_DISABLE_PLUGIN_AUTOLOAD"
OWN_DISTRIBUTION = "vistac"


@dataclass(frozen=True)
class PluginFailure:
    """A plugin that could not be loaded, and why."""

    name: str
    error: str


@dataclass
class Plugins:
    """The loaded plugin set: the pluggy manager (event hooks) and the component registry."""

    manager: pluggy.PluginManager
    registry: Registry
    loaded: list[str] = field(default_factory=list)
    failures: list[PluginFailure] = field(default_factory=list)

    @property
    def hook(self) -> pluggy.HookRelay:
        return self.manager.hook


def _autoload_disabled() -> bool:
    return os.environ.get(AUTOLOAD_ENV, "").strip().lower() not in ("", "0", "false", "no")


def _is_own(ep: EntryPoint) -> bool:
    return ep.dist is not None and ep.dist.name == OWN_DISTRIBUTION


def _selected_entry_points(requested: set[str]) -> list[EntryPoint]:
    autoload = not _autoload_disabled()
    chosen = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if _is_own(ep) or autoload or ep.name in requested:
            chosen.append(ep)
    return sorted(chosen, key=lambda ep: (not _is_own(ep), ep.name))


def _register_module(plugins: Plugins, name: str, module: ModuleType) -> None:
    """Register one plugin module and run its ``vistac_register``; failures are recorded."""
    if plugins.manager.is_registered(module) or name in plugins.loaded:
        return
    plugins.registry.current_plugin = name
    entries_before = plugins.registry.snapshot()
    try:
        plugins.manager.register(module, name=name)
        impl = getattr(module, "vistac_register", None)
        if impl is not None:
            impl(registry=plugins.registry)
    except Exception as exc:  # a broken plugin must not take the others down
        if plugins.manager.is_registered(module):
            plugins.manager.unregister(module)
        plugins.registry.restore(entries_before)  # a skipped plugin registers nothing
        _fail(plugins, name, f"{type(exc).__name__}: {exc}")
        return
    plugins.loaded.append(name)


def _fail(plugins: Plugins, name: str, error: str) -> None:
    log.warning("plugin %s skipped: %s", name, error)
    plugins.failures.append(PluginFailure(name, error))


def load_plugins(requested: Iterable[str] = ()) -> Plugins:
    """Load vistac's plugins, third-party entry points (unless autoload is disabled) and the
    explicitly ``requested`` ones (entry-point names or module paths)."""
    manager = pluggy.PluginManager(ENTRY_POINT_GROUP)
    manager.add_hookspecs(hookspecs)
    plugins = Plugins(manager, Registry())
    wanted = set(requested)
    found_names = set()
    for ep in _selected_entry_points(wanted):
        found_names.add(ep.name)
        try:
            module = ep.load()
        except Exception as exc:
            _fail(plugins, ep.name, f"cannot import {ep.value}: {type(exc).__name__}: {exc}")
            continue
        _register_module(plugins, ep.name, module)
    for name in sorted(wanted - found_names):
        try:
            module = importlib.import_module(name)
        except ImportError as exc:
            _fail(plugins, name, f"no entry point or module named {name!r} ({exc})")
            continue
        _register_module(plugins, name, module)
    return plugins
