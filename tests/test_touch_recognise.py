"""`skills/touch_recognise.yaml` end to end: the class is right and the pose error (two-way
Hausdorff distance of the mesh vertices) falls below 10% of the object size; bad input gives a
clear error. The acceptance runs over all classes and poses are marked slow."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from vistac.cli import main
from vistac.plugins.touch.library import KNOWN, NOVEL

MIN_KNOWN_NOVEL_ACCURACY = 0.75
SKILL = Path(__file__).resolve().parents[1] / "skills" / "touch_recognise.yaml"


def recognise(tmp_path: Path, obj: str, seed: int, *overrides: str) -> dict[str, Any]:
    out = tmp_path / f"{obj}-{seed}"
    args = [
        "-q",
        "run",
        str(SKILL),
        "--out",
        str(out),
        "--seed",
        str(seed),
        "--set",
        f"components.probe.with.object={obj}",
        "--set",
        "rate_hz=500",
    ]
    for override in overrides:
        args += ["--set", override]
    main(args)
    summary: dict[str, Any] = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    return summary


@pytest.mark.parametrize(("obj", "seed"), [("chair", 3), ("guitar", 1)])
def test_a_known_object_is_recognised_and_localised(tmp_path: Path, obj: str, seed: int) -> None:
    summary = recognise(tmp_path, obj, seed)
    assert summary["status"] == "success", summary["error"]
    errors, touch = summary["touch_errors"], summary["touch"]
    assert errors["class_correct"] and touch["mle_class"] == obj
    assert errors["pose_error_m"] < errors["pose_tolerance_m"]
    assert errors["steps_to_pose"] is not None and errors["stopped_by"] == "explorer"
    assert touch["class_probabilities"][obj] > 0.9 and touch["known"] is True
    assert 0 < errors["max_particle_count"] <= 7000
    assert len(touch["mle_pose"]) == 4 and len(touch["history"]) == errors["steps"]


def test_an_absent_object_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        [
            "-q",
            "run",
            str(SKILL),
            "--out",
            str(tmp_path / "x"),
            "--set",
            "rate_hz=500",
            "--set",
            "components.probe.with.position_m=[2.0, 2.0, 2.0]",
        ]
    )
    assert code == 1
    assert "no contact in 30 touches" in capsys.readouterr().err


def test_a_non_watertight_mesh_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "open.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\n", encoding="utf-8")
    code = main(
        [
            "-q",
            "run",
            str(SKILL),
            "--out",
            str(tmp_path / "x"),
            "--set",
            f"components.probe.with.object={path}",
        ]
    )
    assert code != 0
    assert "not watertight" in capsys.readouterr().err


def report(rows: list[dict[str, Any]], key: str) -> float:
    values = [r[key] for r in rows if r[key] is not None]
    return sum(values) / max(len(values), 1)


@pytest.mark.slow
@pytest.mark.parametrize("explorer", ["touch.dhd", "touch.rrt"])
def test_acceptance_every_known_class_at_ten_poses(tmp_path: Path, explorer: str) -> None:
    rows = []
    for obj in KNOWN:
        for seed in range(10):
            summary = recognise(
                tmp_path,
                obj,
                seed,
                f"components.explorer.plugin={explorer}",
                "tree.sequence.0.explore_touch.max_touches=300",
            )
            rows.append(summary["touch_errors"])
    print(
        f"{explorer}: mean steps to pose {report(rows, 'steps_to_pose'):.1f}, "
        f"to termination {report(rows, 'steps'):.1f}"
    )
    assert all(r["class_correct"] for r in rows)
    assert all(r["steps_to_pose"] is not None for r in rows)


@pytest.mark.slow
def test_acceptance_known_or_novel(tmp_path: Path) -> None:
    decisions = []
    for obj in [*KNOWN, *NOVEL]:
        for seed in range(2):
            known = recognise(tmp_path, obj, seed)["touch"]["known"]
            decisions.append(known is (obj in KNOWN))
    accuracy = sum(decisions) / len(decisions)
    print(f"known/novel accuracy {accuracy:.2f} over {len(decisions)} runs")
    assert accuracy >= MIN_KNOWN_NOVEL_ACCURACY
