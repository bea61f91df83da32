"""The YAML behaviour tree: parsing, static checks and construction on py_trees.

Node forms in YAML::

    look                                # a behaviour with default arguments
    {look: {camera: cam2}}              # a behaviour with arguments
    {sequence: [node, ...]}             # also {selector: [...]}; a plain list is a sequence
    {repeat: {do: [node, ...], until: node, max: 10, on_max: success}}

Behaviours are components of kind ``behaviour``: subclasses of :class:`SkillBehaviour`.
"""

from __future__ import annotations

import logging
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Literal

import py_trees
from py_trees.common import Access, Status
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from vistac.component import ComponentConfig
from vistac.errors import ConfigIssue, PluginError, validation_issues
from vistac.registry import Registry, suggest

if TYPE_CHECKING:
    from vistac.run import RunContext

log = logging.getLogger(__name__)

COMPOSITES = ("sequence", "selector", "repeat")


class SkillBehaviour(py_trees.behaviour.Behaviour):
    """Base class of tree nodes. Subclasses define ``Config`` (the node's YAML arguments),
    the blackboard keys they ``reads``/``writes``, and the components they use:
    ``role_fields`` maps a Config field (whose value is a role name in ``components:``) to
    the component kind it must have; fields in ``optional_roles`` may name an absent role."""

    kind: ClassVar[str] = "behaviour"
    reads: ClassVar[tuple[str, ...]] = ()
    optional_reads: ClassVar[tuple[str, ...]] = ()
    writes: ClassVar[tuple[str, ...]] = ()
    role_fields: ClassVar[dict[str, str]] = {}
    optional_roles: ClassVar[tuple[str, ...]] = ()

    class Config(ComponentConfig):
        pass

    def __init__(self, name: str, config: Any, run: RunContext | None) -> None:
        super().__init__(name)
        self.config = config
        self.run = run
        self.bb = self.attach_blackboard_client(name=name)
        for key in (*self.reads, *self.optional_reads):
            self.bb.register_key(key, access=Access.READ)
        for key in self.writes:
            self.bb.register_key(key, access=Access.WRITE)

    @classmethod
    def blackboard_writes(cls, config: Any, roles: dict[str, str]) -> set[str]:
        """Keys this node writes, given the skill's roles -> kinds."""
        return set(cls.writes)

    def component(self, field_name: str) -> Any:
        """The component named by Config field ``field_name`` (None if optional and absent)."""
        assert self.run is not None, "behaviour used outside a run"
        role = getattr(self.config, field_name)
        if field_name in self.optional_roles and not self.run.has_role(role):
            return None
        return self.run.component(role)

    def read(self, key: str, default: Any = None) -> Any:
        return self.bb.get(key) if self.bb.exists(key) else default

    def write(self, key: str, value: Any) -> None:
        self.bb.set(key, value, overwrite=True)


class RepeatArgs(BaseModel):
    model_config = ConfigDict(extra="forbid")

    do: Any
    until: Any = None
    max: int = Field(10, gt=0)
    on_max: Literal["success", "failure"] = "success"


@dataclass
class NodeSpec:
    """A parsed tree node. ``cls``/``config`` are set for behaviours, ``children`` for
    composites; ``until``, ``max_iterations`` and ``on_max`` for ``repeat``."""

    name: str
    path: str
    cls: type[SkillBehaviour] | None = None
    config: Any = None
    children: list[NodeSpec] = field(default_factory=list)
    until: NodeSpec | None = None
    max_iterations: int = 0
    on_max: str = "success"

    def walk(self) -> Iterator[NodeSpec]:
        """Nodes in execution order (a repeat's body before its condition)."""
        yield self
        for child in self.children:
            yield from child.walk()
        if self.until is not None:
            yield from self.until.walk()


TreeSpec = NodeSpec


def _split_node(raw: Any, path: str) -> tuple[str, Any] | ConfigIssue:
    if isinstance(raw, str):
        return raw, None
    if isinstance(raw, list):
        return "sequence", raw
    if isinstance(raw, dict) and len(raw) == 1:
        ((name, value),) = raw.items()
        return str(name), value
    return ConfigIssue(path, "a tree node is a name, a one-key mapping {name: arguments} or a list")


def parse_tree(
    raw: Any, registry: Registry, context: dict[str, Any], path: str = "tree"
) -> tuple[NodeSpec | None, list[ConfigIssue]]:
    """Parse a YAML tree node recursively, collecting every issue."""
    split = _split_node(raw, path)
    if isinstance(split, ConfigIssue):
        return None, [split]
    name, value = split
    if isinstance(raw, list):
        return _parse_children("sequence", value, registry, context, path)
    if name in ("sequence", "selector"):
        return _parse_children(name, value, registry, context, f"{path}.{name}")
    if name == "repeat":
        return _parse_repeat(value, registry, context, f"{path}.repeat")
    return _parse_behaviour(name, value, registry, context, path)


def _parse_children(
    name: str, value: Any, registry: Registry, context: dict[str, Any], path: str
) -> tuple[NodeSpec | None, list[ConfigIssue]]:
    if not isinstance(value, list) or not value:
        return None, [ConfigIssue(path, f"'{name}' needs a non-empty list of nodes")]
    node, issues = NodeSpec(name, path), []
    for index, child_raw in enumerate(value):
        child, child_issues = parse_tree(child_raw, registry, context, f"{path}[{index}]")
        issues += child_issues
        if child is not None:
            node.children.append(child)
    return node, issues


def _parse_repeat(
    value: Any, registry: Registry, context: dict[str, Any], path: str
) -> tuple[NodeSpec | None, list[ConfigIssue]]:
    try:
        args = RepeatArgs.model_validate(value)
    except ValidationError as exc:
        return None, validation_issues(path, exc, RepeatArgs)
    body = args.do if isinstance(args.do, list) else [args.do]
    node, issues = _parse_children("repeat", body, registry, context, f"{path}.do")
    if node is None:
        return None, issues
    node.path, node.max_iterations, node.on_max = path, args.max, args.on_max
    if args.until is not None:
        node.until, until_issues = parse_tree(args.until, registry, context, f"{path}.until")
        issues += until_issues
    return node, issues


def _parse_behaviour(
    name: str, value: Any, registry: Registry, context: dict[str, Any], path: str
) -> tuple[NodeSpec | None, list[ConfigIssue]]:
    node_path = f"{path}.{name}"
    known = registry.names("behaviour")
    if name not in known:
        hint = suggest(name, [*known, *COMPOSITES])
        return None, [ConfigIssue(path, f"unknown tree node {name!r}{hint}")]
    try:
        cls = registry.load(name, "behaviour")
    except PluginError as exc:
        return None, [ConfigIssue(path, str(exc))]
    if value is not None and not isinstance(value, dict):
        return None, [ConfigIssue(node_path, "node arguments must be a mapping")]
    try:
        config = cls.Config.model_validate(value or {}, context=context)
    except ValidationError as exc:
        return None, validation_issues(node_path, exc, cls.Config)
    return NodeSpec(name, node_path, cls=cls, config=config), []


def check_tree(
    tree: NodeSpec,
    kinds: dict[str, str],
    data_flow: bool = True,
    unresolved: Collection[str] = (),
) -> list[ConfigIssue]:
    """Check the roles each node uses and, with ``data_flow``, the blackboard data flow
    (reads after writes; pointless on a tree whose parse left nodes out). Roles in
    ``unresolved`` (components whose own errors are reported) are not checked."""
    issues: list[ConfigIssue] = []
    written: set[str] = set()
    for node in tree.walk():
        if node.cls is None:
            continue
        issues += _role_issues(node, kinds, unresolved)
        for key in node.cls.reads if data_flow else ():
            if key not in written:
                issues.append(
                    ConfigIssue(node.path, f"reads {key!r}, but no earlier node writes it")
                )
        written |= node.cls.blackboard_writes(node.config, kinds)
    return issues


def _role_issues(
    node: NodeSpec, kinds: dict[str, str], unresolved: Collection[str]
) -> list[ConfigIssue]:
    assert node.cls is not None
    issues = []
    for field_name, kind in node.cls.role_fields.items():
        role = getattr(node.config, field_name)
        if role in unresolved:
            continue
        if role not in kinds:
            if field_name not in node.cls.optional_roles:
                hint = suggest(role, list(kinds))
                issues.append(
                    ConfigIssue(
                        node.path,
                        f"needs a {kind} component as role {role!r}; "
                        f"add it under components:{hint}",
                    )
                )
        elif kinds[role] != kind:
            issues.append(
                ConfigIssue(
                    node.path, f"role {role!r} is {_a(kinds[role])}, this node needs {_a(kind)}"
                )
            )
    return issues


class RepeatUntil(py_trees.composites.Composite):
    """Tick the body (a sequence) then the condition, until the condition succeeds or
    ``max_iterations`` bodies have run. A failing body fails the repeat."""

    def __init__(
        self,
        name: str,
        body: py_trees.behaviour.Behaviour,
        until: py_trees.behaviour.Behaviour | None,
        max_iterations: int,
        on_max: str,
    ) -> None:
        super().__init__(name, [body] + ([until] if until is not None else []))
        self.body, self.until = body, until
        self.max_iterations, self.on_max = max_iterations, on_max
        self.iterations = 0

    def tick(self) -> Iterator[py_trees.behaviour.Behaviour]:
        if self.status != Status.RUNNING:
            self.iterations = 0
            self.initialise()
        self.current_child = self.body
        yield from self.body.tick()
        if self.body.status != Status.SUCCESS:
            self._finish(self.body.status)
            yield self
            return
        self.iterations += 1
        if self._condition_met():
            self._finish(Status.SUCCESS)
        elif self.iterations >= self.max_iterations:
            log.info("%s: stopped after %d iterations", self.name, self.iterations)
            self._finish(Status.SUCCESS if self.on_max == "success" else Status.FAILURE)
        else:
            self.status = Status.RUNNING
        yield self

    def _condition_met(self) -> bool:
        if self.until is None:
            return False
        for _ in self.until.tick():
            pass
        return self.until.status == Status.SUCCESS

    def _finish(self, status: Status) -> None:
        self.stop(status)

    def stop(self, new_status: Status = Status.INVALID) -> None:
        py_trees.composites.Composite.stop(self, new_status)


def build_tree(node: NodeSpec, run: RunContext | None) -> py_trees.behaviour.Behaviour:
    """Instantiate py_trees behaviours for a parsed tree (``run`` None: display only)."""
    if node.cls is not None:
        return node.cls(node.name, node.config, run)
    children = [build_tree(child, run) for child in node.children]
    if node.name == "selector":
        return py_trees.composites.Selector("selector", memory=True, children=children)
    if node.name == "repeat":
        body = py_trees.composites.Sequence("do", memory=True, children=children)
        until = build_tree(node.until, run) if node.until is not None else None
        label = f"repeat (max {node.max_iterations}" + (
            f", until {node.until.name})" if node.until else ")"
        )
        return RepeatUntil(label, body, until, node.max_iterations, node.on_max)
    return py_trees.composites.Sequence("sequence", memory=True, children=children)


def _a(noun: str) -> str:
    """``noun`` with its indefinite article: 'an arm', 'a filter'."""
    return f"{'an' if noun[:1] in 'aeiou' else 'a'} {noun}"
