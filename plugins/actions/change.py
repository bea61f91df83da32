"""Change detection (paper 1, IV-B6): does the interaction still match the learned model?

At every filter step the dual filter records the observation likelihood of eq. 37 per
modality, before the step's update (the predictive likelihood; see
``vistac.plugins.filters.dual.modality_log_likelihoods``). ``change_detected`` averages the
chosen modality's log likelihood over a sliding window within the last interaction and
flags a change the first time the window mean falls below ``threshold``. Run it on an
object whose parameters are known (``filters.dual`` ``prior_from`` and
``estimate_parameters: false``), so that a low likelihood means the world changed, not the
belief.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
from py_trees.common import Status
from pydantic import Field
from vistac.component import ComponentConfig
from vistac.errors import ConfigError
from vistac.tree import SkillBehaviour
from vistac.types import FloatArray

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ChangeReport:
    """One interaction: the lowest window mean (the score; lower = less like the model),
    whether it fell below the threshold and how long after the interaction's start (s)."""

    episode: int
    score: float
    flagged: bool
    flagged_after_s: float | None
    window_means: list[float]


def window_means(time_s: FloatArray, values: FloatArray, window_s: float) -> FloatArray:
    """Mean of ``values`` [T] over the trailing window ``(t - window_s, t]`` at each step
    whose window is full (``t - time_s[0] >= window_s``): [T'] with T' <= T (one entry, the
    mean of all, when the interaction is shorter than the window)."""
    starts = np.searchsorted(time_s, time_s - window_s, side="right")
    full = time_s - time_s[0] >= window_s - 1e-9
    if not np.any(full):
        return np.array([float(np.mean(values))])
    totals = np.concatenate([[0.0], np.cumsum(values)])
    ends = np.arange(1, len(values) + 1)
    means = (totals[ends] - totals[starts]) / (ends - starts)
    return np.asarray(means[full], dtype=np.float64)


def assess(
    steps: Sequence[dict[str, Any]], modality: str, window_s: float, threshold: float
) -> ChangeReport:
    """The change report of one interaction's filter steps (``step_history`` entries)."""
    time_s = np.array([step["time_s"] for step in steps], dtype=np.float64)
    values = np.array([step["log_likelihood"][modality] for step in steps], dtype=np.float64)
    means = window_means(time_s, values, window_s)
    below = np.flatnonzero(means < threshold)
    flagged_after_s = None
    if below.size:
        full_ends = time_s[time_s - time_s[0] >= window_s - 1e-9]
        end_s = full_ends[below[0]] if full_ends.size else time_s[-1]
        flagged_after_s = float(end_s - time_s[0])
    return ChangeReport(
        episode=int(steps[0]["episode"]),
        score=float(means.min()),
        flagged=bool(below.size),
        flagged_after_s=flagged_after_s,
        window_means=means.tolist(),
    )


def auroc(changed_scores: Sequence[float], unchanged_scores: Sequence[float]) -> float:
    """Area under the ROC curve of "score below a threshold means changed": the probability
    that a changed interaction scores lower than an unchanged one (ties count half)."""
    changed = np.asarray(changed_scores, dtype=np.float64)[:, None]
    unchanged = np.asarray(unchanged_scores, dtype=np.float64)[None, :]
    if changed.size == 0 or unchanged.size == 0:
        raise ValueError("auroc needs at least one score of each class")
    return float(np.mean((changed < unchanged) + 0.5 * (changed == unchanged)))


class ChangeDetected(SkillBehaviour):
    """Condition: SUCCESS when the last interaction no longer matches the learned model.

    Reads the filter's ``step_history()``; appends a ``ChangeReport`` of the last
    interaction to the summary's ``change_detection`` list (the first flag also sets
    ``change_detected_after_s``). FAILURE without a report when the last action was not
    carried out (``execute_action`` backed off), so no interaction is assessed twice."""

    reads = ("belief",)
    optional_reads = ("episode",)
    role_fields = {"filter": "filter"}

    class Config(ComponentConfig):
        filter: str = "filter"
        modality: Literal["tactile", "visual"] = Field(
            "tactile", description="which observation's likelihood (the paper: tactile)"
        )
        window_s: float = Field(1.0, gt=0, description="sliding window length")
        threshold: float = Field(
            -2.0,
            description="flag when the window mean of the per-entry log likelihood (eq. 37) "
            "falls below this; calibrate on interactions in the unchanged world",
        )

    def update(self) -> Status:
        history = getattr(self.component("filter"), "step_history", None)
        if not callable(history):
            raise ConfigError(
                "change_detected needs a filter that keeps a per-step history (filters.dual)"
            )
        episode = self.read("episode")
        if episode is None:
            self.feedback_message = "the last action was not carried out: nothing to assess"
            return Status.FAILURE
        steps = history()
        if not steps or steps[-1]["episode"] != episode.index:
            raise ConfigError(
                f"change_detected: the filter has no steps of interaction {episode.index}; "
                "put it after update_belief"
            )
        last = [step for step in steps if step["episode"] == episode.index]
        config = self.config
        report = assess(last, config.modality, config.window_s, config.threshold)
        self.run.results.setdefault("change_detection", []).append(asdict(report))
        log.info(
            "interaction %d: %s likelihood score %.2f (threshold %.2f)%s",
            report.episode, config.modality, report.score, config.threshold,
            f", change flagged {report.flagged_after_s:.2f} s after the start"
            if report.flagged else "",
        )  # fmt: skip
        if not report.flagged:
            self.feedback_message = f"no change (score {report.score:.2f})"
            return Status.FAILURE
        self.run.results.setdefault("change_detected_after_s", report.flagged_after_s)
        return Status.SUCCESS
