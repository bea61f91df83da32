"""The context of one run: components by role, seeded random streams, hooks, the recorder
and the clock. Components are built lazily in dependency order and closed in reverse."""

from __future__ import annotations

import logging
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from vistac.errors import SafetyError, VistacError
from vistac.pluginmanager import Plugins
from vistac.recording import RunRecorder
from vistac.skill import Skill

log = logging.getLogger(__name__)

MOTION_KINDS = ("arm", "gripper")


@dataclass(frozen=True)
class RunInfo:
    """What observers are told about the run."""

    skill: str
    skill_path: Path
    out_dir: Path
    seed: int


class SimClock:
    """Simulated time: advancing steps the world's physics (as fast as the CPU allows)."""

    def __init__(self, world: Any) -> None:
        self.world = world

    @property
    def time_s(self) -> float:
        return float(self.world.time_s)

    def start(self) -> None:
        """Nothing to do: simulated time only moves when the world steps."""

    def advance(self, dt_s: float) -> None:
        self.world.step(dt_s)


class WallClock:
    """Wall-clock time (``time.monotonic()``, which hardware plugins use to timestamp their
    data) at a fixed rate; overruns (a tick longer than its period) are counted and logged."""

    def __init__(self) -> None:
        self.deadline_s = time.monotonic()
        self.overruns = 0

    @property
    def time_s(self) -> float:
        return time.monotonic()

    def start(self) -> None:
        """The first control period starts now: the set-up before (building the components,
        which may take seconds) is not an overrun."""
        self.deadline_s = time.monotonic()

    def advance(self, dt_s: float) -> None:
        self.deadline_s += dt_s
        remaining_s = self.deadline_s - time.monotonic()
        if remaining_s > 0:
            time.sleep(remaining_s)
            return
        self.overruns += 1
        if self.overruns == 1:
            log.warning(
                "control period overrun by %.1f ms; later overruns are logged at debug level "
                "and counted in summary.json (control_overruns)", -remaining_s * 1e3,
            )  # fmt: skip
        else:
            log.debug("control period overrun by %.1f ms", -remaining_s * 1e3)
        self.deadline_s = time.monotonic()


class RunContext:
    """Everything a behaviour or component may use during one run."""

    def __init__(self, skill: Skill, plugins: Plugins, recorder: RunRecorder, seed: int) -> None:
        self.skill = skill
        self.plugins = plugins
        self.recorder = recorder
        self._seed = seed
        self.info = RunInfo(skill.name, skill.path, recorder.out_dir, seed)
        self.period_s = 1.0 / skill.rate_hz
        self._built: dict[str, Any] = {}
        self._building: list[str] = []
        self.clock: SimClock | WallClock = WallClock()
        self.episode_count = 0
        self.results: dict[str, Any] = {}
        """Entries behaviours add to summary.json (e.g. ``belief``, ``shape``)."""

    @property
    def skill_dir(self) -> Path:
        return self.skill.skill_dir

    @property
    def seed(self) -> int:
        return self._seed

    @property
    def hook(self) -> Any:
        return self.plugins.hook

    def rng(self, stream: str) -> np.random.Generator:
        """A generator seeded from the run seed and the stream name (stable across runs)."""
        return np.random.default_rng([self._seed, zlib.crc32(stream.encode())])

    def has_role(self, role: str) -> bool:
        return role in self.skill.components

    def roles_of_kind(self, kind: str) -> list[str]:
        return [role for role, c in self.skill.components.items() if c.kind == kind]

    def find(self, kind: str) -> Any | None:
        """The first component of ``kind`` in YAML order, built on demand, or None."""
        roles = self.roles_of_kind(kind)
        return self.component(roles[0]) if roles else None

    def component(self, role: str) -> Any:
        """The component in ``role``, built on first use."""
        if role in self._built:
            return self._built[role]
        if role in self._building:
            chain = " -> ".join([*self._building, role])
            raise VistacError(f"components depend on each other in a cycle: {chain}")
        resolved = self.skill.components[role]
        self._building.append(role)
        try:
            instance = resolved.cls(resolved.config, self)
        finally:
            self._building.pop()
        self._built[role] = instance
        log.debug("built %s (%s)", role, resolved.plugin)
        return instance

    def build_all(self) -> None:
        """Build every component (worlds first) and choose the clock."""
        ordered = sorted(
            self.skill.components, key=lambda r: self.skill.components[r].kind != "world"
        )
        for role in ordered:
            self.component(role)
        world = self.find("world")
        if world is not None and getattr(world, "simulated", False):
            world.reset(self._seed)
            self.clock = SimClock(world)

    @property
    def time_s(self) -> float:
        return self.clock.time_s

    def world_if_built(self) -> Any | None:
        """The world component if it has been built (never builds one)."""
        for role in self.roles_of_kind("world"):
            if role in self._built:
                return self._built[role]
        return None

    def stop_motion(self) -> list[str]:
        """Stop every built arm and gripper; returns the errors met (never raises)."""
        errors = []
        for role, instance in self._built.items():
            if self.skill.components[role].kind in MOTION_KINDS:
                try:
                    instance.stop()
                except Exception as exc:  # stopping must try every device
                    errors.append(f"{role}.stop() failed: {exc}")
                    log.error("%s.stop() failed: %s", role, exc)
        return errors

    def close_all(self) -> None:
        """Release every built component in reverse build order (never raises). A gripper's
        ``close()`` closes its fingers, so a gripper is released by ``release()`` if it has
        one, and never closed."""
        for role in reversed(list(self._built)):
            instance = self._built[role]
            if self.skill.components[role].kind == "gripper":
                release = getattr(instance, "release", None)
            else:
                release = instance.close
            try:
                if release is not None:
                    release()
            except Exception as exc:
                log.error("releasing %s failed: %s", role, exc)
        self._built.clear()

    def check_fresh(self, what: str, timestamp_s: float, max_age_s: float) -> None:
        """Raise SafetyError when sensor data is older than ``max_age_s``."""
        age_s = self.time_s - timestamp_s
        if age_s > max_age_s:
            raise SafetyError(
                f"stale {what} data: {age_s * 1e3:.0f} ms old (limit {max_age_s * 1e3:.0f} ms)"
            )
