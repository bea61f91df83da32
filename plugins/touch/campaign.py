"""``vistac eval`` for touch skills: a set of objects x random poses x explorers, in one run.

Every trial runs the skill (``vistac run``) with the probe's object and the seed (which draws
the object's pose) overridden, and reads the summary's ``touch_errors``. The report
(``eval.json``, ``tables.md``) has, per explorer and object, the share of trials with the right
class, with the pose found (two-way Hausdorff under 10% of the object's size), the mean touches
to the pose and to termination, the share the explorer stopped by itself (not by the touch
budget), the known/novel decision (eq. 28) and the peak particle count. Novel variants are
scored on the known/novel decision only (the right answer for them is "novel"): their class
is in no library.
"""

from __future__ import annotations

import json
import logging
import re
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from vistac.campaign import run_once
from vistac.errors import ConfigError

log = logging.getLogger(__name__)

EXPLORERS = ("dhd", "rrt")


@dataclass(frozen=True)
class TouchEvalOptions:
    """What to evaluate: the skill, the objects (``known``, ``novel``, class names or mesh
    paths), trials (random poses) per object, the explorers, a base seed and ``--set``s."""

    skill: Path
    out: Path
    objects: tuple[str, ...]
    trials: int
    explorers: tuple[str, ...]
    seed: int
    overrides: tuple[str, ...] = ()


def is_touch_skill(skill: Path) -> bool:
    """Whether the skill's components include a touch estimator (``touch.*``)."""
    data = yaml.safe_load(skill.read_text(encoding="utf-8")) or {}
    components = data.get("components") or {}
    return any(str((c or {}).get("plugin", "")).startswith("touch.")
               for c in components.values() if isinstance(c, dict))  # fmt: skip


def parse_explorers(text: str) -> tuple[str, ...]:
    """``dhd,rrt`` -> ("dhd", "rrt"); ConfigError for an unknown name."""
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in EXPLORERS]
    if unknown or not names:
        raise ConfigError(f"--explorers: {','.join(unknown) or 'nothing'} is not one of "
                          f"{', '.join(EXPLORERS)}; e.g. --explorers dhd,rrt")  # fmt: skip
    return names


def select_touch_objects(selection: Sequence[str]) -> list[tuple[str, bool]]:
    """(object, is known) for ``known``, ``novel``, a library name or a mesh path (known when
    it names a known class)."""
    from vistac.plugins.touch.library import KNOWN, NOVEL

    out: list[tuple[str, bool]] = []
    for item in selection:
        if item == "known":
            out += [(name, True) for name in KNOWN]
        elif item == "novel":
            out += [(name, False) for name in NOVEL]
        else:
            out.append((item, item in KNOWN))
    if not out:
        raise ConfigError("--objects: nothing to evaluate; use known, novel or class names")
    return out


def object_folder(obj: str) -> str:
    """The runs' folder name of an object: a library name as is, a mesh path's file stem;
    characters other than letters, digits, ``_``, ``-`` and inner dots become ``_``."""
    name = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(obj).stem).strip(".")
    return name or "object"


def check_object_folders(objects: Sequence[str]) -> None:
    """ConfigError when two different objects would share a runs folder (same file stem)."""
    first: dict[str, str] = {}
    for obj in objects:
        owner = first.setdefault(object_folder(obj), obj)
        if owner != obj:
            raise ConfigError(
                f"--objects: {owner} and {obj} would share the runs folder "
                f"{object_folder(obj)!r} (a mesh file's folder is its file stem); "
                "rename one of the files"
            )


def check_objects_exist(objects: Sequence[str]) -> None:
    """ConfigError for an object that is neither a library shape nor a mesh file there is."""
    from vistac.plugins.touch.library import missing_shape

    for obj in objects:
        problem = missing_shape(obj)
        if problem:
            raise ConfigError(f"--objects: {problem}; check the name or the path")


def _probe_object(obj: str) -> str:
    """The probe's ``object`` for ``obj``: a mesh path absolute (the skill takes a relative
    one from its own folder, the command line from the working folder), a name as is."""
    return str(Path(obj).resolve()) if Path(obj).suffix else obj


def run_trial(options: TouchEvalOptions, obj: str, explorer: str, trial: int) -> dict[str, Any]:
    """Run the skill once (reusing a finished run with the same arguments): the record of
    ``touch_errors`` and the run's wall time."""
    run_dir = options.out / "runs" / explorer / object_folder(obj) / f"trial_{trial:02d}"
    args = ["-q", "run", str(options.skill), "--out", str(run_dir), "--overwrite",
            "--seed", str(options.seed + trial),
            "--set", f"components.probe.with.object={_probe_object(obj)}",
            "--set", f"components.explorer.plugin=touch.{explorer}"]  # fmt: skip
    for override in options.overrides:
        args += ["--set", override]
    log.info("touch eval: %s on %s, trial %d", explorer, obj, trial)
    code, summary = run_once(args, run_dir, "touch eval")
    if code != 0 or summary is None:
        return {"status": "failed", "reason": f"exit code {code}; see {run_dir}"}
    errors = summary.get("touch_errors")
    if not isinstance(errors, dict):
        return {"status": "failed", "reason": f"no touch_errors in {run_dir}/summary.json"}
    return {"status": "ok", "run_dir": str(run_dir),
            "wall_s": summary.get("wall_time_s"), **errors}  # fmt: skip


def _mean(values: Sequence[float]) -> float | None:
    return statistics.fmean(values) if values else None


def aggregate(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The table row of a group of trial records (see the module docstring)."""
    ok = [r for r in records if r["status"] == "ok"]
    known = [r for r in ok if r["is_known"]]
    to_pose = [r["steps_to_pose"] for r in known if r.get("steps_to_pose") is not None]
    decided = [r for r in ok if r.get("known") is not None]
    return {
        "trials": len(records),
        "failed": len(records) - len(ok),
        "known_trials": len(known),
        "class_right": sum(bool(r.get("class_correct")) for r in known),
        "pose_found": len(to_pose),
        "touches_to_pose": _mean(to_pose),
        "touches_to_stop": _mean([r["steps"] for r in ok]),
        "terminated": sum(r.get("stopped_by") == "explorer" for r in ok),
        "decision_right": sum(r["known"] == r["is_known"] for r in decided),
        "decided": len(decided),
        "max_particles": max((r.get("max_particle_count") or 0 for r in ok), default=0),
    }


def evaluate_touch(options: TouchEvalOptions) -> dict[str, Any]:
    """Run every (explorer, object, trial); write and return the report."""
    if options.trials < 1:
        raise ConfigError(f"--trials must be at least 1, got {options.trials}")
    objects = select_touch_objects(options.objects)
    check_object_folders([obj for obj, _ in objects])
    check_objects_exist([obj for obj, _ in objects])
    records = [
        {"explorer": explorer, "object": obj, "is_known": known, "trial": trial}
        | run_trial(options, obj, explorer, trial)
        for explorer in options.explorers
        for obj, known in objects
        for trial in range(options.trials)
    ]
    rows = {explorer: {obj: aggregate([r for r in records
                                       if r["explorer"] == explorer and r["object"] == obj])
                       for obj, _ in objects} | {
                           "all known": aggregate([r for r in records if r["explorer"] == explorer
                                                   and r["is_known"]]),
                           "all novel": aggregate([r for r in records if r["explorer"] == explorer
                                                   and not r["is_known"]])}
            for explorer in options.explorers}  # fmt: skip
    report = {"skill": str(options.skill), "trials": options.trials, "seed": options.seed,
              "records": records, "tables": rows}  # fmt: skip
    options.out.mkdir(parents=True, exist_ok=True)
    (options.out / "eval.json").write_text(json.dumps(report, indent=1), encoding="utf-8")
    (options.out / "tables.md").write_text(tables_markdown(rows), encoding="utf-8")
    return report


def _cell(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def tables_markdown(rows: dict[str, dict[str, dict[str, Any]]]) -> str:
    """One table per explorer."""
    header = ("| object | trials | class right | pose found | touches to pose | touches to stop "
              "| explorer stopped | known/novel right | peak particles |\n"
              "|---|---|---|---|---|---|---|---|---|\n")  # fmt: skip
    parts = []
    for explorer, table in rows.items():
        lines = [f"## touch.{explorer}\n\n", header]
        for obj, row in table.items():
            if row["trials"] == 0:
                continue
            n, k = row["trials"] - row["failed"], row["known_trials"]
            recognition = f"{row['class_right']}/{k} | {row['pose_found']}/{k}" if k else "- | -"
            failed = f" ({row['failed']} failed)" if row["failed"] else ""
            lines.append(
                f"| {obj} | {row['trials']}{failed} | {recognition}"
                f" | {_cell(row['touches_to_pose'])} | {_cell(row['touches_to_stop'])}"
                f" | {row['terminated']}/{n} | {row['decision_right']}/{row['decided']}"
                f" | {row['max_particles']} |\n")  # fmt: skip
        parts.append("".join(lines))
    return "\n".join(parts)
