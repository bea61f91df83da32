"""The training rows of BENCHMARKS.md come from a train.json: known values in, known rows out."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

from training_report import render  # noqa: E402


def _report(tmp_path: Path) -> Path:
    folder = tmp_path / "paper"
    folder.mkdir()
    report = {
        "preset": {"interactions": ["push"], "hidden": 64},
        "data": {
            "train": {"by_type": {"homogeneous/push": 10, "articulated/push": 7,
                                  "homogeneous/pull": 5}},
            "val": {"by_type": {"homogeneous/push": 2, "heterogeneous/push": 1}},
        },
        "collect_time_s": 600.0,
        "push": {
            "gnn": {"history": [{}] * 12, "filter_history": [{}], "time_s": 300.0},
            "ff": {"1_links": {"history": [{}] * 4, "time_s": 60.0},
                   "2_links": {"history": [{}] * 5, "filter_history": [{}], "time_s": 90.0}},
        },
        "time_s": 1500.0,
    }  # fmt: skip
    path = folder / "train.json"
    path.write_text(json.dumps(report), encoding="utf-8")
    return path


def test_rows_give_trajectories_per_link_count_time_and_epochs(tmp_path: Path) -> None:
    rows = render([_report(tmp_path)]).splitlines()
    assert "| paper | push | GNN | 64 | 17 / 3 | 5.0 min | 13 |" in rows
    assert "| paper | push | FF, 1 link | 64 | 10 / 2 | 1.0 min | 4 |" in rows
    assert "| paper | push | FF, 2 links | 64 | 7 / 1 | 1.5 min | 6 |" in rows
    assert any(row.startswith("| paper | all |") and "(10.0 min)" in row and "25.0 min" in row
               for row in rows)  # fmt: skip
    assert render([]) == ""


def test_a_missing_report_is_a_clear_error_before_any_benchmark(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, str(BENCHMARKS / "run_all.py"), "--out", str(tmp_path / "B.md"),
         "--train-report", str(tmp_path / "none" / "train.json")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert result.returncode == 2
    assert "no such train.json" in result.stderr and "vistac train" in result.stderr
    assert not (tmp_path / "B.md").exists()


def test_a_rerun_keeps_the_notes_and_the_earlier_training_section(tmp_path: Path) -> None:
    from run_all import kept_sections

    out = tmp_path / "B.md"
    assert kept_sections(out) == ("", "")
    section = render([_report(tmp_path)])
    notes = "\n## Notes\n\nThe machine was busy.\n"
    out.write_text("# Benchmarks\n\n| old rows |\n" + notes + section, encoding="utf-8")
    assert kept_sections(out) == (notes, section)
    out.write_text("# Benchmarks\n\n| old rows |\n" + section, encoding="utf-8")
    assert kept_sections(out) == ("", section)
    out.write_text("# Benchmarks\n\n| no training |\n" + notes, encoding="utf-8")
    assert kept_sections(out) == (notes, "")
