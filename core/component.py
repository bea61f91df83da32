"""The base class of every component and the context a component is built in.

A component is a class with a nested pydantic ``Config`` (``extra="forbid"``) and a ``kind``
(the role it can fill). It is constructed as ``cls(config, ctx)``: ``ctx`` gives the skill's
folder, its seed and access to the other components (a simulated arm finds the simulated world
with ``ctx.find("world")``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, ClassVar, Protocol

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationInfo


class ComponentConfig(BaseModel):
    """Base of every component's ``Config``: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class ComponentSpec(BaseModel):
    """``{plugin: NAME, with: {...}}``: a component chosen in YAML (also usable nested)."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    plugin: str
    with_: dict[str, Any] = Field(default_factory=dict, alias="with")


def _resolve_skill_path(value: Path, info: ValidationInfo) -> Path:
    base = (info.context or {}).get("skill_dir")
    if base is None or value.is_absolute():
        return value
    return (Path(base) / value).resolve()


SkillPath = Annotated[Path, AfterValidator(_resolve_skill_path)]
"""A path in a config: relative paths are resolved against the skill file's folder."""


class ComponentContext(Protocol):
    """What a component may use while it is built and run."""

    @property
    def skill_dir(self) -> Path: ...

    @property
    def seed(self) -> int: ...

    def rng(self, stream: str) -> np.random.Generator:
        """A generator seeded from the skill seed and ``stream`` (reproducible per name)."""
        ...

    def component(self, role: str) -> Any:
        """The component in ``role`` of the skill (built on demand)."""
        ...

    def find(self, kind: str) -> Any | None:
        """The skill's component of ``kind`` (built on demand), or None when there is none."""
        ...


class Component:
    """Base class for components. Subclasses set ``kind`` and define ``Config``."""

    kind: ClassVar[str] = ""

    class Config(ComponentConfig):
        pass

    def __init__(self, config: Any, ctx: ComponentContext) -> None:
        self.config = config
        self.ctx = ctx

    def close(self) -> None:
        """Release devices and files. Called once at the end of the run, also after
        failures. A gripper releases in ``release()``, since its ``close()`` closes the
        fingers."""
