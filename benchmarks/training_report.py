"""The training rows of BENCHMARKS.md, read from the ``train.json`` that ``vistac train`` wrote.

Training takes tens of minutes, so ``make bench`` does not train: it reports a run done before
(``make bench TRAIN_REPORTS="DIR/train.json ..."``). Per interaction and model: the
trajectories it was trained on, its wall time and the epochs it ran (rollout and end-to-end).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

_LINKS = {"homogeneous": 1, "heterogeneous": 2, "articulated": 2}
"""Links of the generated object types (an FF is trained per link count)."""


def _models(report: dict[str, Any]) -> list[tuple[str, int | None, dict[str, Any]]]:
    """(name, link count or None for all, entry) of every trained model of one interaction."""
    models: list[tuple[str, int | None, dict[str, Any]]] = []
    for name in ("gnn", "ff"):
        entry = report.get(name)
        if entry is None:
            continue
        if "time_s" in entry:
            models.append((name.upper(), None, entry))
        else:  # {"1_links": ..., "2_links": ...}
            for key, sub in entry.items():
                links = int(key.split("_")[0])
                models.append((f"{name.upper()}, {links} link{'s' * (links > 1)}", links, sub))
    return models


def _trajectories(data: dict[str, Any], split: str, kind: str, links: int | None) -> int:
    """Trajectories of the interaction ``kind`` (of objects with ``links`` links) in a split."""
    total = 0
    for key, count in data.get(split, {}).get("by_type", {}).items():
        object_type, _, interaction = key.partition("/")
        if interaction == kind and links in (None, _LINKS.get(object_type)):
            total += count
    return int(total)


def training_lines(path: Path) -> list[str]:
    """Markdown table rows of one train.json."""
    report = json.loads(path.read_text(encoding="utf-8"))
    preset = report.get("preset", {})
    data = report.get("data", {})
    lines = []
    for kind in preset.get("interactions", ()):
        if kind not in report:
            continue
        for name, links, entry in _models(report[kind]):
            epochs = len(entry.get("history", [])) + len(entry.get("filter_history", []))
            train, val = (_trajectories(data, split, kind, links) for split in ("train", "val"))
            lines.append(
                f"| {path.parent.name} | {kind} | {name} | {preset.get('hidden')} | "
                f"{train} / {val} | {entry['time_s'] / 60:.1f} min | {epochs} |"
            )
    total_min = report.get("time_s", 0.0) / 60
    collect_min = report.get("collect_time_s", 0.0) / 60
    lines.append(f"| {path.parent.name} | all | all, with the noise nets and collection "
                 f"({collect_min:.1f} min) | | | {total_min:.1f} min | |")  # fmt: skip
    return lines


HEADING = "## Training"
"""The section's heading starts so (``run_all`` keeps an earlier section by it)."""


def render(paths: list[Path]) -> str:
    """The training section for the reports at ``paths`` ("" for none)."""
    if not paths:
        return ""
    header = [
        "",
        f"{HEADING} (from `vistac train` reports, not rerun by `make bench`)",
        "",
        "| run | interaction | model | hidden | trajectories (train / val) | wall time | epochs |",
        "|---|---|---|---|---|---|---|",
    ]
    return "\n".join(header + [line for path in paths for line in training_lines(path)]) + "\n"
