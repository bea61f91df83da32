"""``update_belief`` and ``belief_converged``: the filter's side of the loop."""

from __future__ import annotations

import fnmatch
import logging

from py_trees.common import Status
from pydantic import Field
from vistac.behaviours.look import shape_links
from vistac.component import ComponentConfig
from vistac.protocols import Scene
from vistac.tree import SkillBehaviour
from vistac.types import GaussianBelief

log = logging.getLogger(__name__)


def record_belief(results: dict[str, object], belief: GaussianBelief) -> None:
    """The summary's latest belief: ``belief`` (mean and std per entry) and
    ``belief_correlation`` (``GaussianBelief.correlation_dict``), which a later run's
    ``prior_from`` reads back."""
    results["belief"] = belief.as_dict()
    results["belief_correlation"] = belief.correlation_dict()


def initial_belief(behaviour: SkillBehaviour, scene: Scene, filter_role: str) -> GaussianBelief:
    """The filter's first belief about the scene's object: written to the blackboard, the
    summary's ``prior`` (what the run started from; ``vistac eval`` scores it) and the
    belief hook. The shape it started from goes to the summary's ``filter_start`` and its
    cloud to ``views/object_cloud.npz``, for ``vistac replay``."""
    belief: GaussianBelief = behaviour.component(filter_role).initialise(scene)
    behaviour.write("belief", belief)
    behaviour.run.results["prior"] = belief.as_dict()
    if scene.shape is not None:  # what ``vistac replay`` starts the filter from again
        behaviour.run.results["filter_start"] = {"links": shape_links(scene.shape)}
        behaviour.run.recorder.save_object_cloud(scene.shape.cloud)
    behaviour.run.hook.vistac_belief(run=behaviour.run.info, belief=belief)
    return belief


DEFAULT_MAX_STD = {"m_*": 0.05, "f_j_*": 0.03, "f_*": 0.03, "com_*": 0.005}


class UpdateBelief(SkillBehaviour):
    """Feed the last episode to the filter (none, when the action was not carried out:
    nothing to do). The summary gets ``belief`` (the latest),
    ``belief_history`` (one per interaction) and, from filters that keep one
    (``step_history()``), ``filter_steps``: the belief at every control step. (A NaN belief
    cannot be built: GaussianBelief rejects it, which stops the run with the arm stopped.)"""

    reads = ("episode", "belief")
    writes = ("belief",)
    role_fields = {"filter": "filter"}

    class Config(ComponentConfig):
        filter: str = "filter"

    def update(self) -> Status:
        episode = self.read("episode")
        if episode is None:  # the action was not carried out (execute_action says why)
            log.info("update_belief: no interaction since the last update; belief unchanged")
            return Status.SUCCESS
        filter_ = self.component("filter")
        belief = filter_.update(episode)
        self.write("belief", belief)
        record_belief(self.run.results, belief)
        self.run.results.setdefault("belief_history", []).append(belief.as_dict())
        steps = getattr(filter_, "step_history", None)
        if callable(steps):  # filters that keep a per-step trace (plots of belief bands)
            self.run.results["filter_steps"] = steps()
        self.run.hook.vistac_belief(run=self.run.info, belief=belief)
        return Status.SUCCESS


class BeliefConverged(SkillBehaviour):
    """SUCCESS when every belief entry matching a pattern of ``max_std`` has a standard
    deviation at or below its limit (the first matching pattern counts; entries matching
    none, such as poses, are ignored)."""

    reads = ("belief",)

    class Config(ComponentConfig):
        max_std: dict[str, float] = Field(
            default_factory=lambda: dict(DEFAULT_MAX_STD),
            description="fnmatch pattern over belief entry names -> largest allowed std",
        )

    def update(self) -> Status:
        belief: GaussianBelief = self.read("belief")
        unconverged = [
            name
            for name, std in zip(belief.names, belief.std, strict=True)
            if (limit := self._limit(name)) is not None and std > limit
        ]
        self.run.results["converged"] = not unconverged
        if unconverged:
            self.feedback_message = "not yet: " + ", ".join(unconverged)
            return Status.FAILURE
        return Status.SUCCESS

    def _limit(self, name: str) -> float | None:
        for pattern, limit in self.config.max_std.items():
            if fnmatch.fnmatchcase(name, pattern):
                return limit
        return None
