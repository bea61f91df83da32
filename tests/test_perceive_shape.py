"""`skills/perceive_shape.yaml` end to end in simulation: every footprint and the two-link
objects are recovered with a Chamfer distance under 1.5 mm per link in at most 4 views."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from vistac.cli import main

SKILLS = Path(__file__).resolve().parents[1] / "skills"
HOMOGENEOUS = [p.stem for p in sorted((SKILLS / "objects").glob("*.yaml"))
               if p.stem not in ("artic_rect_rect", "hetero_rect_tri")]  # fmt: skip
MAX_CHAMFER_M = 0.0015


def perceive(tmp_path: Path, obj: str, *overrides: str) -> dict[str, object]:
    out = tmp_path / obj
    args = ["run", str(SKILLS / "perceive_shape.yaml"), "--out", str(out),
            "--set", f"components.world.with.object=objects/{obj}.yaml"]  # fmt: skip
    for override in overrides:
        args += ["--set", override]
    assert main(args) == 0
    summary: dict[str, object] = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    return summary


@pytest.mark.parametrize(
    "obj",
    [*HOMOGENEOUS, "artic_rect_rect", "hetero_rect_tri"],
)
def test_active_perception_recovers_the_shape(tmp_path: Path, obj: str) -> None:
    summary = perceive(tmp_path, obj)
    errors, shape = summary["shape_errors"], summary["shape"]
    assert isinstance(errors, dict) and isinstance(shape, dict)
    assert errors["links_fitted"] == errors["links_true"]
    assert all(c is not None and c < MAX_CHAMFER_M for c in errors["chamfer_m"]), errors
    assert shape["views"] <= 4
    assert len(shape["links"]) == errors["links_true"]
    assert all(len(link["std"]) == 14 for link in shape["links"])


def test_summary_reports_views_and_time(tmp_path: Path) -> None:
    summary = perceive(tmp_path, "rect1", "components.views={plugin: shape.uniform_views}")
    shape = summary["shape"]
    assert isinstance(shape, dict)
    assert shape["views"] == 4 and shape["time_s"] > 0
    assert summary["views_taken"] == 4


def test_an_empty_scene_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Looking at the sky: no table, no object.
    code = main(["-q", "run", str(SKILLS / "perceive_shape.yaml"), "--out", str(tmp_path / "x"),
                 "--set", "components.views.with.target_m=[0.0, 3.0, 0.03]",
                 "--set", "components.views.with.elevation_deg=5"])  # fmt: skip
    assert code == 1
    assert "object" in capsys.readouterr().err


def test_the_run_prints_the_fitted_links_and_their_chamfer_distance(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    perceive(tmp_path, "rect2", "components.views={plugin: shape.uniform_views}")
    out = capsys.readouterr().out
    assert "shape: 1 link(s)" in out
    assert "link 0: semi-axes" in out and "Chamfer distance to the true links:" in out


CORNER_SKILL = """
version: 1
name: look-twice
seed: 0
rate_hz: 15
components:
  world:  {plugin: sim.mujoco, with: {object: box.yaml}}
  camera: {plugin: sim.depth_camera, with: {width: 160, height: 120}}
  cloud:  {plugin: shape.open3d_cloud}
  there:  {plugin: shape.uniform_views, with: {views: 1, target_m: [-0.36, 0.27, 0.03]}}
  home:   {plugin: shape.uniform_views, with: {views: 1}}
tree:
  sequence:
    - look: {views: there}
    - look: {views: home}
    - stop
"""


def test_a_later_look_aims_where_the_object_was_last_seen(tmp_path: Path) -> None:
    """Pushes can take an object out of the view planner's fixed first view (here its
    default target, (0, 0.45)); a later look whose first view shows no object takes it again,
    aimed where the last look saw the object."""
    box = (SKILLS / "objects" / "rect1.yaml").read_text(encoding="utf-8")
    box = box.replace("- 0.0\n- 0.45\n- 0.0", "- -0.36\n- 0.27\n- 0.3")
    (tmp_path / "box.yaml").write_text(box, encoding="utf-8")
    (tmp_path / "look.yaml").write_text(CORNER_SKILL, encoding="utf-8")
    assert main(["run", str(tmp_path / "look.yaml"), "--out", str(tmp_path / "out")]) == 0
    views = sorted((tmp_path / "out" / "views").glob("0*.npz"))
    assert len(views) == 3  # the second look's first view (no object), and again
    eye_m = np.load(views[1])["world_from_camera"][:3, 3]
    assert abs(eye_m[0]) < 1e-9 and abs(eye_m[1] - (0.45 - 0.5 * np.cos(np.radians(50)))) < 1e-9
    eye_m = np.load(views[2])["world_from_camera"][:3, 3]
    # uniform_views' first view: 0.5 m from its target on the robot side, 50 deg up.
    assert abs(eye_m[0] + 0.36) < 0.02 and eye_m[1] < 0.27 - 0.25
