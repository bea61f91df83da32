"""Runs a validated skill: builds components, ticks the tree once per control period, and
guarantees the arm is stopped on every way out (success, failure, exception, Ctrl-C)."""

from __future__ import annotations

import logging
import platform
import sys
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import py_trees
from py_trees.common import Status
from vistac.errors import SafetyError, VistacError
from vistac.objects import com_in_frames, match_links
from vistac.pluginmanager import Plugins
from vistac.recording import RunRecorder, check_out_dir, prepare_out_dir
from vistac.run import RunContext, SimClock
from vistac.skill import Skill
from vistac.tree import build_tree
from vistac.types import GaussianBelief

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    """Outcome of a run. ``status``: success | failure | error | interrupted;
    ``error_exit_code``: the exit code of the error (2 for invalid input, also when the run
    finds it while it builds its components, e.g. a ``prior_from`` file that is not a
    summary); ``summary``: empty when the run failed before it started (nothing written)."""

    status: str
    out_dir: Path
    summary: dict[str, Any] = field(default_factory=dict)
    error: str | None = None
    error_exit_code: int = 1

    @property
    def exit_code(self) -> int:
        codes = {"success": 0, "interrupted": 130, "error": self.error_exit_code}
        return codes.get(self.status, 1)


def _versions() -> dict[str, str]:
    names = (
        "vistac",
        "numpy",
        "scipy",
        "mujoco",
        "py_trees",
        "pluggy",
        "pydantic",
        "torch",
        "open3d",
    )
    found = {"python": platform.python_version()}
    for name in names:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            continue
    return found


def run_info(skill: Skill, plugins: Plugins, seed: int) -> dict[str, Any]:
    return {
        "skill": skill.name,
        "skill_path": str(skill.path),
        "seed": seed,
        "config": skill.raw,
        "plugins": plugins.loaded,
        "versions": _versions(),
        "machine": {"platform": platform.platform(), "processor": platform.machine()},
        "command": sys.argv,
        "started_unix_s": time.time(),
        "status": "running",
    }


class Scheduler:
    """Ticks one skill's tree under its clock."""

    def __init__(
        self,
        skill: Skill,
        plugins: Plugins,
        out_dir: Path,
        seed: int | None = None,
        overwrite: bool = False,
    ) -> None:
        check_out_dir(out_dir, overwrite)  # the folder is made once the run has started
        self.overwrite = overwrite
        self.skill = skill
        self.seed = skill.seed if seed is None else seed
        self.recorder = RunRecorder(out_dir)
        self.ctx = RunContext(skill, plugins, self.recorder, self.seed)
        self.run_info = run_info(skill, plugins, self.seed)
        self.ticks = 0

    def run(self) -> RunResult:
        """Run to completion. Never raises for failures: they are in the result.

        A run that fails while it sets up (its components and tree, e.g. a checkpoint that
        is not there) has not started: it writes nothing, so the same ``--out`` takes the run
        once the input is fixed, and its result has no summary. From the first tick on the
        folder records the run, and any failure with it."""
        py_trees.blackboard.Blackboard.clear()
        wall_start_s = time.perf_counter()
        result = RunResult("error", self.recorder.out_dir)
        started = False
        try:
            tree = self._set_up()
            prepare_out_dir(self.recorder.out_dir, self.overwrite)
            started = True
            self.recorder.write_run(self.run_info)
            result.status = self._tick_until_done(tree)
        except KeyboardInterrupt:
            result.status, result.error = "interrupted", "interrupted by Ctrl-C"
        except Exception as exc:  # every failure path ends with the arm stopped
            result.error = (
                str(exc) if isinstance(exc, VistacError) else f"{type(exc).__name__}: {exc}"
            )
            result.error_exit_code = exc.exit_code if isinstance(exc, VistacError) else 1
            log.debug("run failed", exc_info=True)
        finally:
            stop_errors = self.ctx.stop_motion()
        if stop_errors:
            result.status, result.error_exit_code = "error", 1
            result.error = "; ".join(filter(None, [result.error, *stop_errors]))
        if started:
            result.summary = self._finish(result, time.perf_counter() - wall_start_s)
        else:
            self.ctx.close_all()
        return result

    def _set_up(self) -> py_trees.trees.BehaviourTree:
        """Build every component and the tree."""
        self.ctx.build_all()
        tree = py_trees.trees.BehaviourTree(build_tree(self.skill.tree, self.ctx))
        tree.setup()
        return tree

    def _tick_until_done(self, tree: py_trees.trees.BehaviourTree) -> str:
        root = tree.root
        self.ctx.hook.vistac_skill_start(run=self.ctx.info)
        self.ctx.clock.start()
        start_s = self.ctx.time_s
        while True:
            tree.tick()
            self.ticks += 1
            self.ctx.hook.vistac_tick(run=self.ctx.info, tick=self.ticks, time_s=self.ctx.time_s)
            if root.status in (Status.SUCCESS, Status.FAILURE):
                return "success" if root.status == Status.SUCCESS else "failure"
            if self.ctx.time_s - start_s > self.skill.max_duration_s:
                tree.interrupt()
                raise SafetyError(
                    f"skill exceeded max_duration_s = {self.skill.max_duration_s:g} s"
                )
            self.ctx.clock.advance(self.ctx.period_s)

    def _finish(self, result: RunResult, wall_s: float) -> dict[str, Any]:
        summary = self._summary(result, wall_s)
        try:
            self.ctx.hook.vistac_skill_end(run=self.ctx.info, status=result.status, summary=summary)
        except Exception as exc:
            log.error("an observer failed at skill end: %s", exc)
        self.ctx.close_all()
        self.recorder.write_summary(summary)
        self.run_info.update(
            status=result.status, error=result.error, wall_time_s=wall_s, ticks=self.ticks
        )
        self.recorder.write_run(self.run_info)
        return summary

    def _summary(self, result: RunResult, wall_s: float) -> dict[str, Any]:
        summary: dict[str, Any] = {
            "skill": self.skill.name,
            "status": result.status,
            "error": result.error,
            "seed": self.seed,
            "wall_time_s": wall_s,
            "sim_time_s": self.ctx.time_s if isinstance(self.ctx.clock, SimClock) else None,
            "control_overruns": getattr(self.ctx.clock, "overruns", None),
            "ticks": self.ticks,
            "views": self.recorder.views,
            "episodes": self.recorder.episodes,
        }
        summary.update(self.ctx.results)
        world = self.ctx.world_if_built()
        truth = world.ground_truth() if world is not None else None
        summary["ground_truth"] = truth
        add_belief_errors(summary)
        return summary


def add_belief_errors(summary: dict[str, Any]) -> None:
    """``belief_truth`` and ``errors`` (|estimate - truth| per entry) of a summary whose
    ``ground_truth`` has the parameters; nothing otherwise."""
    belief, truth = summary.get("belief"), summary.get("ground_truth")
    if belief and truth and "parameters" in truth:
        summary["belief_truth"] = belief_truth(belief, truth)
        summary["errors"] = {
            name: abs(entry["mean"] - summary["belief_truth"][name])
            for name, entry in belief.items()
            if name in summary["belief_truth"]
        }


def belief_truth(belief: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """The true value of each belief parameter entry: a belief link's ``m_b``, ``f_b``,
    ``com_x_b``, ``com_y_b`` are those of the true link nearest it, the CoM in the belief's
    frame of link b (a fitted frame, whose origin and yaw differ from the link frame's) where
    the belief puts it at the end; other entries (``f_j_k``) by name. Without the belief's
    or the true link poses, entries compare by name."""
    parameters: dict[str, float] = truth["parameters"]
    n_belief = GaussianBelief.link_count(belief)
    if "link_poses" not in truth or not all(f"theta_{b}" in belief for b in range(n_belief)):
        return dict(parameters)
    frames = GaussianBelief.link_poses(belief, range(n_belief))
    link_poses = np.asarray(truth["link_poses"], dtype=np.float64).reshape(-1, 3)
    links = match_links(frames[:, :2], link_poses[:, :2])
    moved = com_in_frames(parameters, links, frames, link_poses)
    by_belief = {name: value for name, value in moved.items() if name.startswith("f_j_")}
    for b, t in links.items():
        for key in ("m", "f", "com_x", "com_y"):
            by_belief[f"{key}_{b}"] = moved[f"{key}_{t}"]
    return by_belief
