"""Skill files: loading, command-line overrides and complete validation.

Validation happens before anything is built or moves, and reports every problem at once with
its YAML path: the file's structure, each component's plugin name and ``with:`` block against
its ``Config``, each tree node's name and arguments, the roles a node uses, and that every
blackboard key a node reads is written by an earlier node.
"""

from __future__ import annotations

import re
from collections.abc import Hashable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from vistac.component import ComponentSpec
from vistac.errors import ConfigError, ConfigIssue, PluginError, suggest, validation_issues
from vistac.registry import Registry
from vistac.tree import TreeSpec, check_tree, parse_tree

MAX_SEED = 2**32 - 1
"""The largest seed a skill or ``--seed`` takes (the simulator and torch take 64-bit seeds, and
evaluations add the trial to it)."""


class SkillFile(BaseModel):
    """Top level of a skill YAML."""

    model_config = ConfigDict(extra="forbid")

    version: Literal[1]
    name: str
    description: str = ""
    seed: int = Field(0, ge=0, le=MAX_SEED, description="seeds every random stream of the run")
    rate_hz: float = Field(15.0, gt=0, description="control and observation rate")
    max_duration_s: float = Field(
        3600.0, gt=0, description="abort the run after this much (sim or wall) time"
    )
    components: dict[str, ComponentSpec] = Field(default_factory=dict)
    tree: Any


@dataclass
class ResolvedComponent:
    """A validated component: its plugin name, kind, class and parsed config."""

    role: str
    plugin: str
    kind: str
    cls: type
    config: BaseModel


@dataclass
class Skill:
    """A validated skill, ready to run."""

    path: Path
    name: str
    seed: int
    rate_hz: float
    max_duration_s: float
    raw: dict[str, Any]
    components: dict[str, ResolvedComponent]
    tree: TreeSpec

    @property
    def skill_dir(self) -> Path:
        return self.path.parent


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a mapping key given twice (safe_load keeps the last)."""


def _construct_unique_mapping(
    loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False
) -> dict[Any, Any]:
    seen: set[Any] = set()
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node, deep=deep)
        if not isinstance(key, Hashable):
            continue  # construct_mapping reports it
        if key in seen:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        seen.add(key)
    return loader.construct_mapping(node, deep)


_UniqueKeyLoader.add_constructor(
    yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_unique_mapping
)


def read_yaml(path: Path) -> Any:
    """Safe-load a YAML file; a missing or malformed file is one clear ConfigError line."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError([ConfigIssue("", "file not found")], str(path)) from None
    except OSError as exc:
        raise ConfigError(
            [ConfigIssue("", f"cannot read file: {exc.strerror}")], str(path)
        ) from None
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise ConfigError(
            [ConfigIssue("", f"malformed YAML: {where}{problem}")], str(path)
        ) from None


def parse_override(text: str) -> tuple[list[str], Any]:
    """``"components.arm.with.max_speed_mps=0.01"`` -> (key path, YAML-parsed value)."""
    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError([ConfigIssue("--set", f"{text!r} is not of the form key.path=value")])
    try:
        parsed = yaml.safe_load(value) if value.strip() else ""
    except yaml.YAMLError as exc:
        if value.lstrip().startswith(("{", "[")):  # meant as a mapping or list: say why not
            problem = getattr(exc, "problem", None) or "not valid YAML"
            issue = ConfigIssue("--set", f"{key.strip()}: {problem} in {value!r}")
            raise ConfigError([issue]) from None
        parsed = value  # a plain string that YAML cannot read, e.g. 'a: b: c'
    return key.strip().split("."), parsed


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Set each ``key.path=value`` in ``data``; integer keys index lists
    (``tree.sequence.1.repeat.max=2``); missing mapping keys are created."""
    for text in overrides:
        keys, value = parse_override(text)
        node: Any = data
        for depth, key in enumerate(keys):
            where = ".".join(keys[: depth + 1])
            last = depth == len(keys) - 1
            if isinstance(node, list):
                if not key.isdigit() or int(key) >= len(node):
                    raise ConfigError([ConfigIssue("--set", f"{where}: no list item {key!r}")])
                index: Any = int(key)
            elif isinstance(node, dict):
                index = key
                if not last and node.get(key) is None:
                    node[key] = {}
            else:
                raise ConfigError(
                    [ConfigIssue("--set", f"{where}: cannot set inside a {type(node).__name__}")]
                )
            if last:
                node[index] = value
            else:
                node = node[index]
    return data


def validate_config(
    cls: type, data: dict[str, Any], path: str, context: dict[str, Any]
) -> tuple[BaseModel | None, list[ConfigIssue]]:
    """Validate a ``with:`` block against ``cls.Config``."""
    config_cls = cls.Config  # type: ignore[attr-defined]
    try:
        return config_cls.model_validate(data, context=context), []
    except ValidationError as exc:
        return None, validation_issues(path, exc, config_cls)


def _resolve_component(
    path: str, spec: ComponentSpec, registry: Registry, context: dict[str, Any]
) -> tuple[ResolvedComponent | None, list[ConfigIssue]]:
    role = path.rsplit(".", 1)[-1]
    try:
        info = registry.info(spec.plugin)
        if info.kind == "behaviour":
            raise PluginError(f"{spec.plugin!r} is a tree node, not a component")
        cls = registry.load(spec.plugin)
    except PluginError as exc:
        return None, [ConfigIssue(f"{path}.plugin", str(exc))]
    config, issues = validate_config(cls, spec.with_, f"{path}.with", context)
    issues += _nested_issues(config, f"{path}.with", registry, context) if config else []
    if config is None or issues:
        return None, issues
    return ResolvedComponent(role, spec.plugin, info.kind, cls, config), []


def _nested_issues(
    config: BaseModel, path: str, registry: Registry, context: dict[str, Any]
) -> list[ConfigIssue]:
    """Validate component specs nested in a config (e.g. a filter's process model)."""
    issues: list[ConfigIssue] = []
    for field_name in type(config).model_fields:
        value = getattr(config, field_name)
        if isinstance(value, ComponentSpec):
            issues += _resolve_component(f"{path}.{field_name}", value, registry, context)[1]
    return issues


def load_skill(path: Path, registry: Registry, overrides: list[str] | None = None) -> Skill:
    """Read, override and fully validate a skill; raises ConfigError listing every problem."""
    path = Path(path)
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError([ConfigIssue("", "a skill file must be a YAML mapping")], str(path))
    return validate_skill(apply_overrides(data, overrides or []), path, registry)


def validate_skill(data: dict[str, Any], path: Path, registry: Registry) -> Skill:
    """Validate skill data as if read from ``path`` (relative paths resolve next to it).
    A top-level error still lets the components and the tree be checked, so that every
    problem is reported at once."""
    try:
        skill_file: SkillFile | None = SkillFile.model_validate(data)
        issues: list[ConfigIssue] = []
    except ValidationError as exc:
        skill_file, issues = None, validation_issues("", exc, SkillFile)
        issues = _name_roles_without_plugin(issues, data.get("components"))
    context = {"skill_dir": path.parent.resolve()}
    specs = skill_file.components if skill_file else _well_formed_specs(data.get("components"))
    components, component_issues = _resolve_components(specs, registry, context)
    issues += component_issues
    tree, tree_issues = _check_tree(data, specs, registry, context)
    issues += tree_issues
    if issues:
        raise ConfigError(issues, str(path))
    assert skill_file is not None and tree is not None
    return Skill(
        path.resolve(),
        skill_file.name,
        skill_file.seed,
        skill_file.rate_hz,
        skill_file.max_duration_s,
        data,
        components,
        tree,
    )


def _name_roles_without_plugin(issues: list[ConfigIssue], raw: Any) -> list[ConfigIssue]:
    """Explain a component without a plugin: most often a misspelt role, since a ``--set``
    key that names no component makes a new one. The roles close to it are named."""
    specs = raw.items() if isinstance(raw, dict) else []
    roles = [str(role) for role, spec in specs if isinstance(spec, dict) and "plugin" in spec]
    named = []
    for issue in issues:
        role = re.fullmatch(r"components\.([^.]+)\.plugin", issue.path)
        if role and issue.message == "Field required":
            close = suggest(role[1], roles) or f" (the other components: {', '.join(roles)})"
            issue = ConfigIssue(issue.path, f"missing: every component names its plugin{close}")
        named.append(issue)
    return named


def _well_formed_specs(raw: Any) -> dict[str, ComponentSpec]:
    """The component specs of a skill that failed top-level validation that are well formed
    (the malformed ones are among the top-level issues)."""
    if not isinstance(raw, dict):
        return {}
    specs = {}
    for role, spec in raw.items():
        try:
            specs[str(role)] = ComponentSpec.model_validate(spec)
        except ValidationError:
            continue
    return specs


def _check_tree(
    data: dict[str, Any],
    specs: dict[str, ComponentSpec],
    registry: Registry,
    context: dict[str, Any],
) -> tuple[TreeSpec | None, list[ConfigIssue]]:
    """Parse the tree and check its roles and data flow; a role whose component did not
    resolve (its error is reported already) is not checked."""
    if "tree" not in data:
        return None, []  # reported as missing by the top-level validation
    tree, issues = parse_tree(data["tree"], registry, context)
    if tree is None:
        return None, issues
    kinds = {
        role: registry.info(spec.plugin).kind
        for role, spec in specs.items()
        if spec.plugin in registry.names()
    }
    roles = data["components"] if isinstance(data.get("components"), dict) else {}
    unresolved = {str(role) for role in roles} - set(kinds)
    return tree, issues + check_tree(tree, kinds, not issues, unresolved)


def _resolve_components(
    specs: dict[str, ComponentSpec], registry: Registry, context: dict[str, Any]
) -> tuple[dict[str, ResolvedComponent], list[ConfigIssue]]:
    components: dict[str, ResolvedComponent] = {}
    issues: list[ConfigIssue] = []
    for role, spec in specs.items():
        resolved, found = _resolve_component(f"components.{role}", spec, registry, context)
        issues += found
        if resolved is not None:
            components[role] = resolved
    return components, issues
