"""The component registry: ``(kind, name) -> "module:Class"``, imported only when used."""

from __future__ import annotations

import importlib
import logging
from dataclasses import dataclass

from pydantic import BaseModel
from vistac.errors import PluginError, suggest
from vistac.protocols import KINDS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ComponentInfo:
    """One registered component."""

    kind: str
    name: str
    target: str
    plugin: str


def import_target(target: str) -> type:
    """Import ``"package.module:Class"``; errors name the target and the cause."""
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise PluginError(f"{target!r} is not of the form 'package.module:Class'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise PluginError(f"cannot import {module_name!r} for {target!r}: {exc}") from exc
    try:
        obj = getattr(module, attr)
    except AttributeError:
        raise PluginError(f"module {module_name!r} has no attribute {attr!r}") from None
    if not isinstance(obj, type):
        raise PluginError(f"{target!r} is not a class")
    return obj


class Registry:
    """Component names by kind. Plugins call :meth:`add` from ``vistac_register``."""

    def __init__(self) -> None:
        self._entries: dict[str, ComponentInfo] = {}
        self._loaded: dict[str, type] = {}
        self.current_plugin = "<direct>"

    def add(self, kind: str, name: str, target: str) -> None:
        """Register ``name`` of ``kind`` implemented by ``target`` = ``"module:Class"``."""
        if kind not in KINDS:
            raise PluginError(f"unknown component kind {kind!r}{suggest(kind, list(KINDS))}")
        if ":" not in target:
            raise PluginError(f"{name}: target {target!r} is not of the form 'module:Class'")
        existing = self._entries.get(name)
        if existing is not None:
            raise PluginError(
                f"component name {name!r} registered twice "
                f"(by {existing.plugin} and {self.current_plugin})"
            )
        self._entries[name] = ComponentInfo(kind, name, target, self.current_plugin)

    def names(self, kind: str | None = None) -> list[str]:
        return sorted(n for n, e in self._entries.items() if kind is None or e.kind == kind)

    def info(self, name: str, kind: str | None = None) -> ComponentInfo:
        """The entry for ``name``; unknown names get a suggestion."""
        entry = self._entries.get(name)
        if entry is None or (kind is not None and entry.kind != kind):
            what = f"{kind} " if kind else ""
            raise PluginError(f"unknown {what}plugin {name!r}{suggest(name, self.names(kind))}")
        return entry

    def load(self, name: str, kind: str | None = None) -> type:
        """Import and check the class registered as ``name``."""
        if name in self._loaded:
            return self._loaded[name]
        entry = self.info(name, kind)
        cls = import_target(entry.target)
        config = getattr(cls, "Config", None)
        if not (isinstance(config, type) and issubclass(config, BaseModel)):
            raise PluginError(f"{entry.target} has no pydantic 'Config' class")
        declared = getattr(cls, "kind", entry.kind)
        if declared != entry.kind:
            raise PluginError(
                f"{entry.target} declares kind {declared!r}, registered as {entry.kind!r}"
            )
        self._loaded[name] = cls
        return cls

    def snapshot(self) -> dict[str, ComponentInfo]:
        """The entries as they are now, for :meth:`restore`."""
        return dict(self._entries)

    def restore(self, snapshot: dict[str, ComponentInfo]) -> None:
        """Back to a :meth:`snapshot` (what a plugin that failed to register added goes)."""
        self._entries = dict(snapshot)

    def entries(self) -> list[ComponentInfo]:
        return sorted(self._entries.values(), key=lambda e: (e.kind, e.name))
