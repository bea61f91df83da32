"""``vistac eval`` for goal-pushing skills (paper 1, IV-B5, Fig. 16): estimated against
default parameters, on a set of objects x trials.

Every trial runs the skill (``vistac run``) twice with the object and the seed overridden:
once as written (the filter estimates the parameters) and once with
``estimate_parameters=false`` (the prior's parameters are kept: the default). Trial ``k``
uses seed ``SEED + k``, which draws the camera noise, the exploratory pushes and iCEM's
samples; the simulated world is deterministic, so the object starts at its file's pose. Each
run is scored by the summary's ``goal_push`` record: the true final position error (m) of the
tracked point and turn error (rad), the pushes planned towards the goal and whether the skill
believed the goal reached. The report (``eval.json``, ``tables.md``) gives per object and
overall the mean and median final position error of both modes and in how many trials the
estimated parameters ended nearer the goal than the default ones.
"""

from __future__ import annotations

import difflib
import json
import logging
import math
import statistics
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from vistac.campaign import run_once
from vistac.errors import ConfigError

log = logging.getLogger(__name__)

MODES = ("estimated", "default")
"""Parameter modes compared: the filter's estimate, and the prior kept (the baseline)."""

_MODE_OVERRIDES = {
    "estimated": (),
    "default": ("components.filter.with.estimate_parameters=false",),
}


@dataclass(frozen=True)
class GoalEvalOptions:
    """What to evaluate: the skill, the objects (names in the skill's ``objects/`` folder,
    comma-separated, ``all`` or object YAML paths), trials per object, the first seed (None:
    the skill's) and ``--set`` overrides applied to every run."""

    skill: Path
    out: Path
    objects: tuple[str, ...]
    trials: int
    seed: int | None = None
    overrides: tuple[str, ...] = ()


def _node_names(tree: Any) -> Iterator[str]:
    """Every behaviour and composite name in a YAML tree (dict keys and bare strings)."""
    if isinstance(tree, str):
        yield tree
    elif isinstance(tree, list):
        for item in tree:
            yield from _node_names(item)
    elif isinstance(tree, dict):
        for key, value in tree.items():
            yield str(key)
            yield from _node_names(value)


def _load_skill(skill: Path) -> dict[str, Any]:
    data = yaml.safe_load(skill.read_text(encoding="utf-8")) or {}
    return data if isinstance(data, dict) else {}


def is_goal_skill(skill: Path) -> bool:
    """Whether the skill's tree plans pushes to a goal (has a ``plan_push`` node)."""
    return "plan_push" in _node_names(_load_skill(skill).get("tree"))


def select_goal_objects(selection: Sequence[str], objects_dir: Path) -> list[Path]:
    """Object files for names in ``objects_dir`` (items may be comma-separated), ``all`` (every
    file there) or paths to object YAML files; ConfigError for an unknown name."""
    available = {path.stem: path for path in sorted(objects_dir.glob("*.yaml"))}
    names = [name.strip() for item in selection for name in item.split(",") if name.strip()]
    paths: list[Path] = []
    for name in names:
        if name == "all":
            paths += available.values()
        elif name in available:
            paths.append(available[name])
        elif name.endswith((".yaml", ".yml")) and Path(name).is_file():
            paths.append(Path(name))
        elif name.endswith((".yaml", ".yml")):
            raise ConfigError(f"--objects: no such file {name}; check the path, or give "
                              f"object names in {objects_dir}")  # fmt: skip
        else:
            close = difflib.get_close_matches(name, available, n=1)
            hint = f"did you mean {close[0]}? " if close else ""
            raise ConfigError(f"--objects: no object {name!r} in {objects_dir}; {hint}"
                              f"use all or some of {', '.join(available) or '(none)'}")  # fmt: skip
    if not paths:
        raise ConfigError("--objects: nothing to evaluate; e.g. --objects rect1,tri1 or all")
    return list(dict.fromkeys(paths))


def _run_args(options: GoalEvalOptions, obj: Path, trial: int, mode: str) -> list[str]:
    """The ``vistac run`` arguments of one run (``options.seed`` set)."""
    seed = (options.seed or 0) + trial
    args = ["-q", "run", str(options.skill), "--out", str(_run_dir(options, obj, trial, mode)),
            "--overwrite", "--seed", str(seed),
            "--set", f"components.world.with.object={obj.resolve()}"]  # fmt: skip
    for override in (*options.overrides, *_MODE_OVERRIDES[mode]):
        args += ["--set", override]
    return args


def score_run(summary: dict[str, Any]) -> dict[str, Any]:
    """The record of one finished run from its summary's ``goal_push``."""
    goal = summary.get("goal_push") or {}
    if "true_error_m" not in goal:
        reason = summary.get("error") or "no true final error in goal_push (simulation only)"
        return {"status": "failed", "reason": f"{summary.get('status')}: {reason}"}
    return {
        "status": "ok",
        "position_error_m": goal["true_error_m"],
        "turn_error_rad": goal["true_turn_error_rad"],
        "believed_error_m": goal.get("believed_error_m"),
        "pushes": len(goal.get("planned_cost_m", [])),
        "goal_reached": bool(goal.get("reached")),
        "skill_status": summary.get("status"),
        "wall_s": summary.get("wall_time_s"),
    }


def _run_dir(options: GoalEvalOptions, obj: Path, trial: int, mode: str) -> Path:
    return options.out / "runs" / mode / obj.stem / f"trial_{trial:02d}"


def run_trial(options: GoalEvalOptions, obj: Path, trial: int, mode: str) -> dict[str, Any]:
    """Run (or reuse) one object x trial x mode (``options.seed`` set); its record."""
    run_dir = _run_dir(options, obj, trial, mode)
    log.info("goal eval: %s parameters on %s, trial %d", mode, obj.stem, trial)
    code, summary = run_once(_run_args(options, obj, trial, mode), run_dir, "goal eval")
    record = {"object": obj.stem, "trial": trial, "seed": (options.seed or 0) + trial,
              "mode": mode, "run_dir": str(run_dir)}  # fmt: skip
    if summary is None:
        return record | {"status": "failed", "reason": f"exit code {code}, no summary; "
                                                       f"see {run_dir}"}
    return record | score_run(summary)


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


def _median(values: Sequence[float]) -> float | None:
    return statistics.median(values) if values else None


def _mode_row(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Means and medians of one mode's successful records."""
    errors_m = [r["position_error_m"] for r in records]
    return {
        "runs": len(records),
        "position_error_mean_m": _mean(errors_m),
        "position_error_median_m": _median(errors_m),
        "turn_error_mean_rad": _mean([r["turn_error_rad"] for r in records]),
        "pushes_mean": _mean([r["pushes"] for r in records]),
        "reached": sum(r["goal_reached"] for r in records),
    }


def paired_difference(
    pairs: Sequence[dict[str, float]], seed: int = 0, level: float = 0.9
) -> dict[str, float] | None:
    """Estimated minus default final position error (m), the mean over the trials ``pairs``
    ({mode: error}), with a ``level`` percentile interval from resampling the trials
    (:func:`~vistac.plugins.filters.evaluate.resampled_interval`; an interval that holds 0
    does not rank the two); None without trials."""
    from vistac.plugins.filters.evaluate import resampled_interval

    if not pairs:
        return None
    differences = np.array([pair["estimated"] - pair["default"] for pair in pairs])
    low, high = resampled_interval(
        lambda draws: differences[draws].mean(-1), len(differences), seed, level
    )
    return {"mean_m": float(differences.mean()), "low_m": low, "high_m": high}


def aggregate(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The table row of a group of records: per mode, and the trials (object, trial) with
    both modes done, in how many of which the estimated parameters ended nearer the goal, and
    by how much on average (:func:`paired_difference`)."""
    ok = [r for r in records if r["status"] == "ok"]
    by_trial: dict[tuple[str, int], dict[str, float]] = {}
    for r in ok:
        by_trial.setdefault((r["object"], r["trial"]), {})[r["mode"]] = r["position_error_m"]
    pairs = [errors for errors in by_trial.values() if len(errors) == len(MODES)]
    return {
        "runs": len(records),
        "failed": len(records) - len(ok),
        **{mode: _mode_row([r for r in ok if r["mode"] == mode]) for mode in MODES},
        "paired_trials": len(pairs),
        "estimated_lower": sum(e["estimated"] < e["default"] for e in pairs),
        "estimated_minus_default": paired_difference(pairs),
    }


def _first_seed(options: GoalEvalOptions) -> int:
    if options.seed is not None:
        return options.seed
    seed = _load_skill(options.skill).get("seed", 0)
    return seed if isinstance(seed, int) else 0


def evaluate_goal(options: GoalEvalOptions) -> dict[str, Any]:
    """Run every (object, trial, mode); write and return the report."""
    if options.trials < 1:
        raise ConfigError(f"--trials must be at least 1, got {options.trials}")
    if not is_goal_skill(options.skill):
        raise ConfigError(f"{options.skill}: no plan_push in the tree; the goal evaluation "
                          "needs a goal-pushing skill such as skills/goal_push.yaml")  # fmt: skip
    objects = select_goal_objects(options.objects, options.skill.parent / "objects")
    options = replace(options, seed=_first_seed(options))
    records = [run_trial(options, obj, trial, mode)
               for obj in objects for trial in range(options.trials) for mode in MODES]  # fmt: skip
    rows = {obj.stem: aggregate([r for r in records if r["object"] == obj.stem])
            for obj in objects} | {"all": aggregate(records)}  # fmt: skip
    report = {"skill": str(options.skill), "trials": options.trials, "seed": options.seed,
              "records": records, "tables": rows}  # fmt: skip
    options.out.mkdir(parents=True, exist_ok=True)
    (options.out / "eval.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    (options.out / "tables.md").write_text(tables_markdown(rows, records), encoding="utf-8")
    return report


def _mm(value_m: float | None) -> str:
    return "-" if value_m is None else f"{value_m * 1e3:.1f}"


def _deg(value_rad: float | None) -> str:
    return "-" if value_rad is None else f"{math.degrees(value_rad):.1f}"


def _number(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _difference(value: dict[str, float] | None) -> str:
    if value is None:
        return "-"
    return "{:+.1f} [{:+.1f}, {:+.1f}]".format(
        *(value[key] * 1e3 for key in ("mean_m", "low_m", "high_m"))
    )


def _pair(row: dict[str, Any], key: str, cell: Callable[[float | None], str]) -> str:
    return " / ".join(cell(row[mode][key]) for mode in MODES)


def tables_markdown(rows: dict[str, dict[str, Any]], records: Sequence[dict[str, Any]]) -> str:
    """One table: per object and overall, estimated / default in each cell."""
    lines = ["# Goal pushing: estimated / default parameters\n\n",
             "Final error of the true object pose (simulation); each cell is estimated / "
             "default.\n\n",
             "| object | trials | mean position error (mm) | median position error (mm) "
             "| mean turn error (deg) | goal pushes | believed reached | estimated lower "
             "| estimated - default (mm, 90 %) |\n",
             "|---|---|---|---|---|---|---|---|---|\n"]  # fmt: skip
    for obj, row in rows.items():
        failed = f" ({row['failed']} runs failed)" if row["failed"] else ""
        reached = " / ".join(f"{row[m]['reached']}/{row[m]['runs']}" for m in MODES)
        lines.append(
            f"| {obj} | {row['paired_trials']}{failed} | {_pair(row, 'position_error_mean_m', _mm)}"
            f" | {_pair(row, 'position_error_median_m', _mm)}"
            f" | {_pair(row, 'turn_error_mean_rad', _deg)} | {_pair(row, 'pushes_mean', _number)}"
            f" | {reached} | {row['estimated_lower']}/{row['paired_trials']}"
            f" | {_difference(row['estimated_minus_default'])} |\n")  # fmt: skip
    wall_s = sum(r.get("wall_s") or 0.0 for r in records)
    lines.append("\nEstimated - default: the mean over the trials of the difference in final "
                 "position error, with a 90 % interval from resampling the trials (one that "
                 "holds 0 does not rank the two).\n")
    lines.append(f"\n{len(records)} runs, {wall_s / 60:.1f} min of skill wall time.\n")
    return "".join(lines)
