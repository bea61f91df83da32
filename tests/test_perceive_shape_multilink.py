"""Skill-level multi-link shape recovery: ``perceive_shape`` on the two-link objects."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from vistac.cli import main

ROOT = Path(__file__).resolve().parents[1]
CHAMFER_TOL_M = 0.0015


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    "artic_rect_rect",
    pytest.param("hetero_rect_tri", marks=pytest.mark.xfail(
        strict=False, reason="the triangle link grows into the rectangle's hidden volume "
        "(2.7-13 mm) in some runs; the views differ between runs")),
])
def test_two_link_objects_are_recovered(name: str, tmp_path: Path,
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Both links are fitted, each within 1.5 mm Chamfer of its true prism."""
    monkeypatch.chdir(ROOT)
    code = main(["-q", "run", "skills/perceive_shape.yaml", "--out", str(tmp_path),
                 "--overwrite", "--set", f"components.world.with.object=objects/{name}.yaml"])
    assert code == 0
    errors = json.loads((tmp_path / "summary.json").read_text())["shape_errors"]
    assert errors["links_fitted"] == 2
    assert all(c is not None and c < CHAMFER_TOL_M for c in errors["chamfer_m"])
