"""Hook specifications. Plugins implement these with ``@vistac.hookimpl``.

``vistac_register`` adds components; every other hook is an event for observers (recorders,
loggers, live viewers, metrics). Event hooks receive the :class:`vistac.run.RunInfo` of the
run as ``run``; they must not block for long, since they are called from the control loop.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import pluggy

if TYPE_CHECKING:
    from vistac.protocols import Episode, StepObservation
    from vistac.registry import Registry
    from vistac.run import RunInfo
    from vistac.types import Action, GaussianBelief

hookspec = pluggy.HookspecMarker("vistac")


@hookspec
def vistac_register(registry: Registry) -> None:
    """Register components: ``registry.add(kind, name, "module:Class")``.

    The class is imported only when a skill uses it, so keep this module free of heavy imports.
    """


@hookspec
def vistac_skill_start(run: RunInfo) -> None:
    """The skill validated, its components are built, and the first tick is next."""


@hookspec
def vistac_tick(run: RunInfo, tick: int, time_s: float) -> None:
    """The tree was ticked once (one control period)."""


@hookspec
def vistac_observation(run: RunInfo, episode: int, step: int, observation: StepObservation) -> None:
    """One observation was recorded during an interaction."""


@hookspec
def vistac_belief(run: RunInfo, belief: GaussianBelief) -> None:
    """The belief was initialised or updated."""


@hookspec
def vistac_action(run: RunInfo, episode: int, action: Action) -> None:
    """An action was chosen and is about to be executed."""


@hookspec
def vistac_episode_end(run: RunInfo, episode: Episode) -> None:
    """An interaction finished and was recorded."""


@hookspec
def vistac_skill_end(run: RunInfo, status: str, summary: dict[str, Any]) -> None:
    """The skill ended (``status`` is ``"success"``, ``"failure"`` or ``"error"``)."""
