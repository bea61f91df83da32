"""Tree nodes for touch: ``explore_touch`` (one touch per tick) and ``recognised``."""

from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np
from py_trees.common import Status
from pydantic import Field
from vistac.component import ComponentConfig
from vistac.errors import DataError
from vistac.tree import SkillBehaviour
from vistac.types import FloatArray

log = logging.getLogger(__name__)

JSON_TYPES = (str, int, float, bool, list, dict, type(None))


class ExploreTouch(SkillBehaviour):
    """One touch per tick: the explorer picks (start, target), the probe moves, the
    estimator (the particle filter) and then the optional ``surface`` estimator (the GPIS)
    update; their dicts are merged into the blackboard key ``touch``. SUCCESS when the
    explorer returns None or after ``max_touches``; a clear error when no touch made contact
    in ``max_touches_without_contact``. The run summary gets ``touch`` (the last estimate, the
    per-step history with the pose error when the probe knows the truth) and ``touch_truth``."""

    writes = ("touch",)
    role_fields = {
        "probe": "touch_probe",
        "explorer": "touch_explorer",
        "estimator": "touch_estimator",
        "surface": "touch_estimator",
    }
    optional_roles = ("surface",)

    class Config(ComponentConfig):
        probe: str = "probe"
        explorer: str = "explorer"
        estimator: str = "estimator"
        surface: str = "surface"
        max_touches: int = Field(150, gt=0)
        max_touches_without_contact: int = Field(30, gt=0)

    def initialise(self) -> None:
        self.estimate: dict[str, Any] = {}
        self.history: list[dict[str, Any]] = []
        self.touches = 0
        self.busy_s = 0.0
        self.stopped_by = ""
        self._truth = _Truth.of(self.component("probe"), self.run)
        self._rng = self.run.rng("touch")

    def update(self) -> Status:
        if self.touches >= self.config.max_touches:
            return self._finish("max_touches")
        start_s = time.perf_counter()
        proposal = self.component("explorer").next_touch(self.estimate, self._rng)
        if proposal is None:
            return self._finish("explorer")
        start, target = (np.asarray(v, dtype=np.float64) for v in proposal)
        contact = self.component("probe").probe(start, target)
        self.estimate = self._update_estimators(start, target, contact)
        self.touches += 1
        self.busy_s += time.perf_counter() - start_s
        self._record(contact is not None)
        self._check_contact()
        return Status.RUNNING

    def _update_estimators(
        self, start: FloatArray, target: FloatArray, contact: tuple[FloatArray, FloatArray] | None
    ) -> dict[str, Any]:
        estimate = dict(self.component("estimator").update(start, target, contact))
        surface = self.component("surface")
        if surface is not None:
            estimate.update(surface.update(start, target, contact))
        self.write("touch", estimate)
        return estimate

    def _record(self, contact: bool) -> None:
        entry: dict[str, Any] = {
            "touch": self.touches,
            "contact": contact,
            "mle_class": self.estimate.get("mle_class"),
            "probability": (self.estimate.get("class_probabilities") or {}).get(
                self.estimate.get("mle_class"), None
            ),
            "particle_count": self.estimate.get("particle_count"),
            "known": self.estimate.get("known"),
            "dhd_m": getattr(self.component("explorer"), "last_dhd_m", None),
        }
        if self._truth is not None:
            entry["pose_error_m"] = self._truth.pose_error_m(self.component("estimator"))
        self.history.append(entry)
        self._publish()

    def _check_contact(self) -> None:
        if self.estimate.get("contacts") or self.touches < self.config.max_touches_without_contact:
            return
        raise DataError(
            f"no contact in {self.touches} touches: the object is not where the probe "
            "explores; check that it lies inside the explorer's workspace "
            "(workspace_centre_m, workspace_half_extent_m)"
        )

    def _finish(self, reason: str) -> Status:
        self.stopped_by = reason
        if not self.estimate.get("contacts"):
            raise DataError(f"no contact in {self.touches} touches: nothing to recognise")
        self._publish()
        return Status.SUCCESS

    def _publish(self) -> None:
        summary = {k: v for k, v in self.estimate.items() if isinstance(v, JSON_TYPES)}
        summary.update(
            touches=self.touches,
            time_s=self.busy_s,
            stopped_by=self.stopped_by,
            history=self.history,
        )
        self.run.results["touch"] = summary
        if self._truth is not None:
            self.run.results["touch_truth"] = self._truth.info


class _Truth:
    """The probe's ground truth, for the pose error (TWD of mesh vertices, eq. 46) only."""

    def __init__(self, info: dict[str, Any], vertices_m: FloatArray, size_m: float) -> None:
        self.info = info
        self.vertices_m = vertices_m
        self.info["size_m"] = size_m

    @classmethod
    def of(cls, probe: Any, run: Any) -> _Truth | None:
        truth = getattr(probe, "ground_truth", None)
        info = truth() if callable(truth) else None
        if not info or "world_from_object" not in info:
            return None
        from vistac.plugins.touch.library import resolve_shape
        from vistac.plugins.touch.meshes import apply_pose

        mesh = resolve_shape(info["object"], run.skill_dir)
        pose = np.asarray(info["world_from_object"])
        return cls(dict(info), apply_pose(pose, mesh.vertices_m), float(mesh.extent_m.max()))

    def pose_error_m(self, estimator: Any) -> float | None:
        from vistac.plugins.touch.metrics import two_way_hausdorff

        mle_prior = getattr(estimator, "mle_prior", None)
        prior = mle_prior() if callable(mle_prior) else None
        return None if prior is None else two_way_hausdorff(self.vertices_m, prior.vertices_m)


class Recognised(SkillBehaviour):
    """SUCCESS when the most likely class has probability >= ``min_probability`` and the
    MLE pose moved less than ``max_pose_change_m`` / ``max_pose_change_deg`` since the last
    tick this node ran; FAILURE otherwise."""

    reads = ("touch",)

    class Config(ComponentConfig):
        min_probability: float = Field(0.95, gt=0, le=1)
        max_pose_change_m: float = Field(0.005, gt=0)
        max_pose_change_deg: float = Field(5.0, gt=0)

    def initialise(self) -> None:
        self._last_pose: FloatArray | None = getattr(self, "_last_pose", None)

    def update(self) -> Status:
        estimate = self.read("touch") or {}
        pose = estimate.get("mle_pose")
        probabilities = estimate.get("class_probabilities") or {}
        if pose is None or not probabilities:
            return Status.FAILURE
        pose = np.asarray(pose)
        steady = self._last_pose is not None and self._steady(self._last_pose, pose)
        self._last_pose = pose
        confident = max(probabilities.values()) >= self.config.min_probability
        self.run.results["recognised"] = bool(confident and steady)
        return Status.SUCCESS if confident and steady else Status.FAILURE

    def _steady(self, before: FloatArray, after: FloatArray) -> bool:
        moved_m = float(np.linalg.norm(after[:3, 3] - before[:3, 3]))
        cos = (np.trace(before[:3, :3].T @ after[:3, :3]) - 1.0) / 2.0
        turned_deg = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        return (
            moved_m <= self.config.max_pose_change_m
            and turned_deg <= self.config.max_pose_change_deg
        )
