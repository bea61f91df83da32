"""Test doubles registered as a plugin (``-p fixtures_plugin``): an arm that records stop
calls, behaviours that count, fail or raise, a toy filter with a known answer, one that cannot
be built and a selector that first sends the fingers down on the object."""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
from py_trees.common import Status
from vistac import hookimpl
from vistac.component import Component, ComponentConfig
from vistac.errors import ConfigError, DataError
from vistac.protocols import Episode, Scene, StepObservation
from vistac.tree import SkillBehaviour
from vistac.types import ArmState, GaussianBelief, Push, TactileReading

STOP_CALLS: list[str] = []


class RecordingArm(Component):
    """An arm that only records what it is told; its clock is the test's."""

    kind = "arm"

    class Config(ComponentConfig):
        max_speed_mps: float = 0.025
        timestamp_s: float | None = None
        build_s: float = 0.0
        """How long building the arm takes (as a real driver's connection may)."""

    max_speed_mps = 0.025

    def __init__(self, config: Config, ctx: Any) -> None:
        super().__init__(config, ctx)
        time.sleep(config.build_s)
        self.twist = np.zeros(4)

    def state(self) -> ArmState:
        return ArmState(np.zeros(4), self.twist, self.config.timestamp_s or 0.0)

    def command_velocity(self, twist: np.ndarray) -> None:
        self.twist = np.asarray(twist, dtype=float)

    def stop(self) -> None:
        self.twist = np.zeros(4)
        STOP_CALLS.append("stop")


class Count(SkillBehaviour):
    """Increments ``count`` on the blackboard each tick, RUNNING for ``ticks`` ticks first."""

    writes = ("count",)
    optional_reads = ("count",)

    class Config(ComponentConfig):
        ticks: int = 1

    def initialise(self) -> None:
        self.left = self.config.ticks

    def update(self) -> Status:
        self.left -= 1
        if self.left > 0:
            return Status.RUNNING
        self.write("count", self.read("count", 0) + 1)
        return Status.SUCCESS


class CountAtLeast(SkillBehaviour):
    """SUCCESS once ``count >= n``."""

    reads = ("count",)

    class Config(ComponentConfig):
        n: int = 3

    def update(self) -> Status:
        return Status.SUCCESS if self.read("count") >= self.config.n else Status.FAILURE


class Boom(SkillBehaviour):
    """Raises ``error`` on its first tick (or KeyboardInterrupt)."""

    class Config(ComponentConfig):
        error: str = "data"

    def update(self) -> Status:
        if self.config.error == "interrupt":
            raise KeyboardInterrupt
        if self.config.error == "data":
            raise DataError("boom: synthetic sensor failure")
        if self.config.error == "config":
            raise ConfigError("boom: synthetic invalid input")
        raise RuntimeError("boom: synthetic bug")


class Fail(SkillBehaviour):
    class Config(ComponentConfig):
        pass

    def update(self) -> Status:
        return Status.FAILURE


class Forever(SkillBehaviour):
    class Config(ComponentConfig):
        pass

    def update(self) -> Status:
        return Status.RUNNING


class NeedsWidget(SkillBehaviour):
    """Reads a key nobody writes (for data-flow validation)."""

    reads = ("widget",)

    class Config(ComponentConfig):
        pass

    def update(self) -> Status:
        return Status.SUCCESS


def measurement_episode(index: int, values: np.ndarray) -> Episode:
    """An episode at 15 Hz whose arm x positions are ``values`` (the toy filter's data)."""
    steps = [
        StepObservation(
            i / 15,
            TactileReading(np.zeros((2, 2)), i / 15),
            ArmState(np.array([v, 0, 0, 0]), np.zeros(4), i / 15),
        )
        for i, v in enumerate(values)
    ]
    return Episode(index, Push(np.zeros(2), 0.0, 0.02), steps)


class FakeInteraction(SkillBehaviour):
    """Writes an episode of 15 noisy measurements of ``value`` (as arm x), initialising the
    belief from the filter the first time, like choose_action + execute_action."""

    optional_reads = ("belief",)
    writes = ("episode", "belief")

    class Config(ComponentConfig):
        value: float = 0.7
        noise_std: float = 0.2

    def update(self) -> Status:
        if self.read("belief") is None:
            self.write("belief", self.run.component("filter").initialise(None))
        rng = self.run.rng(f"fake/{self.run.episode_count}")
        values = self.config.value + rng.normal(0, self.config.noise_std, 15)
        self.write("episode", measurement_episode(self.run.episode_count, values))
        self.run.episode_count += 1
        return Status.SUCCESS


class ScalarKalmanFilter(Component):
    """Estimates a constant scalar ``m_0`` from noisy measurements in ``episode.steps``
    (the arm's x position stands in for the measurement). Known answer: the Kalman filter."""

    kind = "filter"

    class Config(ComponentConfig):
        prior_mean: float = 0.0
        prior_var: float = 1.0
        noise_var: float = 0.01
        nan_after: int | None = None

    names: ClassVar[tuple[str, ...]] = ("m_0",)

    def initialise(self, scene: Scene) -> GaussianBelief:
        self.mean, self.var, self.updates = self.config.prior_mean, self.config.prior_var, 0
        return self._belief()

    def update(self, episode: Episode) -> GaussianBelief:
        for step in episode.steps:
            gain = self.var / (self.var + self.config.noise_var)
            self.mean += gain * (step.arm.pose[0] - self.mean)
            self.var *= 1 - gain
        self.updates += 1
        if self.config.nan_after is not None and self.updates > self.config.nan_after:
            self.mean = float("nan")  # a diverged filter
        return self._belief()

    def _belief(self) -> GaussianBelief:
        return GaussianBelief(np.array([self.mean]), np.array([[self.var]]), self.names)


class BrokenAtBuild(Component):
    """A filter whose input is bad: building it raises a ConfigError (a checkpoint that is
    not there, say)."""

    kind = "filter"

    def __init__(self, config: ComponentConfig, ctx: Any) -> None:
        raise ConfigError("broken: synthetic checkpoint that is not there")


class OntoTheObjectFirst(Component):
    """A selector whose first choice is the first candidate push moved ``inward_m`` along its
    direction, so that the fingers come down on the object; later it takes the candidate
    nearest the scene's first blocked point (the first candidate when there is none)."""

    kind = "action_selector"

    class Config(ComponentConfig):
        inward_m: float = 0.035

    def __init__(self, config: Config, ctx: Any) -> None:
        super().__init__(config, ctx)
        self.config: OntoTheObjectFirst.Config = config
        self.calls = 0

    def select(self, candidates: Any, scene: Scene, rng: np.random.Generator) -> Any:
        self.calls += 1
        first = candidates[0]
        if self.calls > 1:
            if not len(scene.blocked_xy_m):
                return first
            points = np.array([action.cp_m for action in candidates])
            gaps_m = np.linalg.norm(points - scene.blocked_xy_m[0], axis=1)
            return candidates[int(gaps_m.argmin())]
        heading = np.array([np.cos(first.pd_rad), np.sin(first.pd_rad)])
        return Push(first.cp_m + self.config.inward_m * heading, first.pd_rad, first.speed_mps,
                    first.duration_s, link=first.link)  # fmt: skip


@hookimpl
def vistac_register(registry: Any) -> None:
    module = __name__
    registry.add("arm", "test.arm", f"{module}:RecordingArm")
    registry.add("action_selector", "test.onto_object_first", f"{module}:OntoTheObjectFirst")
    registry.add("filter", "test.kalman", f"{module}:ScalarKalmanFilter")
    registry.add("filter", "test.broken", f"{module}:BrokenAtBuild")
    for name, cls in {
        "count": "Count",
        "count_at_least": "CountAtLeast",
        "boom": "Boom",
        "fail": "Fail",
        "forever": "Forever",
        "needs_widget": "NeedsWidget",
        "fake_interaction": "FakeInteraction",
    }.items():
        registry.add("behaviour", name, f"{module}:{cls}")
