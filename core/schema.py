"""JSON Schema of skill files, generated from the registered components' ``Config`` classes."""

from __future__ import annotations

import logging
from typing import Any

from pydantic.json_schema import models_json_schema
from vistac.errors import PluginError
from vistac.registry import Registry
from vistac.skill import SkillFile

log = logging.getLogger(__name__)


def skill_schema(registry: Registry) -> dict[str, Any]:
    """The skill-file schema: each component's ``with:`` is checked against its plugin's
    Config (``if plugin == NAME then with: Config``); tree nodes' arguments are in ``$defs``."""
    loaded: dict[str, type] = {}
    for entry in registry.entries():
        try:
            loaded[entry.name] = registry.load(entry.name)
        except PluginError as exc:
            log.warning("schema: skipping %s: %s", entry.name, exc)
    configs: dict[str, Any] = {name: cls.Config for name, cls in loaded.items()}  # type: ignore[attr-defined]
    keys: dict[str, Any] = {name: (config, "validation") for name, config in configs.items()}
    refs, top = models_json_schema(list(keys.values()), ref_template="#/$defs/{model}")
    schema = SkillFile.model_json_schema(ref_template="#/$defs/{model}")
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "vistac skill"
    schema.setdefault("$defs", {}).update(top.get("$defs", {}))
    components = [n for n in loaded if registry.info(n).kind != "behaviour"]
    nodes = [n for n in loaded if registry.info(n).kind == "behaviour"]
    schema["properties"]["components"] = {
        "type": "object",
        "additionalProperties": {
            "type": "object",
            "required": ["plugin"],
            "additionalProperties": False,
            "properties": {"plugin": {"enum": sorted(components)}, "with": {"type": "object"}},
            "allOf": [
                {
                    "if": {"properties": {"plugin": {"const": name}}},
                    "then": {"properties": {"with": refs[keys[name]]}},
                }
                for name in sorted(components)
            ],
        },
    }
    schema["properties"]["tree"] = {
        "description": "a node: NAME | {NAME: args} | [nodes] | {sequence: [...]} | "
        "{selector: [...]} | {repeat: {do, until, max, on_max}}; nodes: "
        + ", ".join(sorted(nodes)),
    }
    schema["x-tree-nodes"] = {name: refs[keys[name]] for name in sorted(nodes)}
    return schema
