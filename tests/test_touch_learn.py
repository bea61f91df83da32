"""Shape learning by touch: saving a learned shape, its error metric, the comparison with
screened Poisson reconstruction (paper 2, Table II) and the touch_learn skill."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import SKILLS
from scipy.spatial.transform import Rotation
from vistac.errors import DataError
from vistac.plugins.touch.gpis import SurfaceMesh, enclosed_volume_m3, extract_surface, sphere_sdf
from vistac.plugins.touch.learning import (
    add_learning_metrics,
    available_path,
    compare_with_poisson,
    outward,
    poisson_reconstruction,
    reconstruction_error_m,
    save_learned_shape,
)
from vistac.plugins.touch.library import KNOWN, NOVEL, known_class, resolve_shape
from vistac.plugins.touch.meshes import Mesh, apply_pose, load_mesh

CENTRE = np.array([0.02, 0.5, 0.3])


def sphere_surface(radius_m: float = 0.05) -> SurfaceMesh:
    """A marching-cubes sphere (world frame) around CENTRE."""
    return extract_surface(lambda p: sphere_sdf(CENTRE, radius_m)(p)[0],
                           CENTRE - 0.08, CENTRE + 0.08, grid_points=32)  # fmt: skip


def a_pose() -> np.ndarray:
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    pose[:3, 3] = CENTRE
    return pose


def test_saved_shape_is_watertight_in_the_object_frame(tmp_path: Path) -> None:
    surface, pose = sphere_surface(), a_pose()
    path = save_learned_shape(surface, tmp_path / "lib", "ball", pose)
    assert path == tmp_path / "lib" / "ball.ply"
    loaded = load_mesh(path, size_m=None)  # validates watertightness
    np.testing.assert_allclose(apply_pose(pose, loaded.vertices_m), surface.vertices_m, atol=1e-6)
    assert enclosed_volume_m3(SurfaceMesh(loaded.vertices_m, loaded.triangles)) > 0.0
    assert save_learned_shape(surface, tmp_path / "lib", "ball", pose).name == "ball_2.ply"
    assert available_path(tmp_path / "lib", "ball").name == "ball_3.ply"


def test_the_saved_path_is_absolute_and_logged(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A relative directory gives the resolved path (listable in touch.pf's classes as is)."""
    monkeypatch.chdir(tmp_path)
    with caplog.at_level("INFO", logger="vistac.plugins.touch.learning"):
        path = save_learned_shape(sphere_surface(), Path("lib"), "ball", a_pose())
    assert path.is_absolute() and path == tmp_path.resolve() / "lib" / "ball.ply"
    assert f"to {path}" in caplog.text


def test_a_learned_shape_is_a_class_of_its_saved_size_and_frame(tmp_path: Path) -> None:
    """A 0.1 m sphere saved in the object frame of a pose 4 cm off its centre, loaded back as
    a class (a path, as in touch.pf's classes): neither rescaled to 0.2 m nor re-centred."""
    surface, pose = sphere_surface(0.05), a_pose()
    pose[:3, 3] += [0.03, -0.02, 0.02]
    path = save_learned_shape(surface, tmp_path, "ball_learned", pose)
    saved = load_mesh(path, size_m=None)
    as_class = resolve_shape(path.name, tmp_path)
    assert as_class.name == "ball_learned"
    np.testing.assert_allclose(as_class.extent_m, saved.extent_m, atol=1e-9)
    assert 0.095 < as_class.extent_m.max() < 0.101
    np.testing.assert_allclose(as_class.vertices_m.min(axis=0), saved.vertices_m.min(axis=0))
    centre = apply_pose(pose, as_class.vertices_m).mean(axis=0)
    np.testing.assert_allclose(centre, surface.vertices_m.mean(axis=0), atol=1e-6)


def test_an_open_surface_is_not_saved(tmp_path: Path) -> None:
    surface = sphere_surface()
    open_surface = SurfaceMesh(surface.vertices_m, surface.triangles[10:])
    with pytest.raises(DataError, match="watertight"):
        save_learned_shape(open_surface, tmp_path, "broken", np.eye(4))
    assert not (tmp_path / "broken.ply").exists()


def test_reconstruction_error_known_answers() -> None:
    small, large = sphere_surface(0.04), sphere_surface(0.05)
    same = reconstruction_error_m((small.vertices_m, small.triangles),
                                  (small.vertices_m, small.triangles))  # fmt: skip
    assert same < 1e-5
    apart = reconstruction_error_m((small.vertices_m, small.triangles),
                                   (large.vertices_m, large.triangles))  # fmt: skip
    assert apart == pytest.approx(0.01, abs=0.001)


def test_outward_fixes_inward_meshes() -> None:
    mesh = known_class("cone")
    flipped = Mesh("cone", mesh.vertices_m, mesh.triangles[:, ::-1].copy())
    for candidate in (mesh, flipped):
        fixed = outward(candidate)
        assert enclosed_volume_m3(SurfaceMesh(fixed.vertices_m, fixed.triangles)) > 0.0


def test_poisson_peer_reconstructs_a_dense_sphere() -> None:
    normals = np.random.default_rng(0).normal(size=(2000, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    mesh = poisson_reconstruction(CENTRE + 0.05 * normals, normals, depth=6)
    radii = np.linalg.norm(mesh.vertices_m - CENTRE, axis=1)
    assert abs(np.median(radii) - 0.05) < 0.003


def test_learning_metrics_measure_the_saved_shape(tmp_path: Path) -> None:
    truth_mesh = known_class("cone")
    pose = a_pose()
    world = SurfaceMesh(apply_pose(pose, truth_mesh.vertices_m), truth_mesh.triangles)
    path = save_learned_shape(world, tmp_path, "cone_copy", pose)
    summary: dict[str, Any] = {
        "learned_shape": {"saved": True, "path": str(path), "world_from_saved": pose.tolist()},
        "touch_truth": {"object": "cone", "world_from_object": pose.tolist()},
        "touch": {"touches": 42},
    }
    add_learning_metrics(summary, tmp_path)
    assert summary["learned_shape"]["steps"] == 42
    assert summary["learned_shape"]["reconstruction_error_m"] < 1e-4
    assert summary["learned_shape"].get("poisson_error_m") is None  # no contacts in the summary
    points, normals = truth_mesh.transformed(pose).surface_samples(400)
    summary["touch"].update(contacts=points.tolist(), normals=normals.tolist())
    add_learning_metrics(summary, tmp_path)
    assert 0.0 < summary["learned_shape"]["poisson_error_m"] < 0.02  # dense: Poisson is good
    shifted = pose.copy()
    shifted[:3, 3] += [0.03, 0.0, 0.0]
    summary["touch_truth"]["world_from_object"] = shifted.tolist()
    add_learning_metrics(summary, tmp_path)
    assert summary["learned_shape"]["reconstruction_error_m"] == pytest.approx(0.03, abs=0.001)


# --- Table II: GPIS with the MLE prior vs screened Poisson on the same sparse contacts -------


@pytest.mark.parametrize("novel", ["hammer_claw", "guitar_long_neck"])
def test_gpis_with_mle_prior_beats_poisson_on_sparse_contacts(novel: str) -> None:
    result = compare_with_poisson(novel, contacts=30, seed=1)
    assert result.gpis_m < result.poisson_m
    assert result.gpis_m < result.mle_m


@pytest.mark.slow
def test_table_ii_gpis_beats_poisson_for_most_novel_classes() -> None:
    results = [compare_with_poisson(name, contacts=40, seed=index)
               for index, name in enumerate(NOVEL)]  # fmt: skip
    lines = [f"{r.name:18s} MLE {r.mle_m:.4f}  GPIS {r.gpis_m:.4f}  Poisson {r.poisson_m:.4f} m"
             for r in results]  # fmt: skip
    print("\n" + "\n".join(lines))
    wins = sum(r.gpis_m < r.poisson_m for r in results)
    assert wins >= 7, "\n".join(lines)


# --- the skill ---------------------------------------------------------------------------


def run_learn(cli: Callable[..., tuple[int, str, str]], out: Path, *overrides: str) -> dict:
    """Run skills/touch_learn.yaml in-process with ``--set`` overrides; its summary."""
    sets = [arg for override in overrides for arg in ("--set", override)]
    code, _, err = cli("run",
                       str(SKILLS / "touch_learn.yaml"), "--out", str(out), *sets)  # fmt: skip
    assert code == 0, err
    return dict(json.loads((out / "summary.json").read_text()))


def test_short_touch_learn_run_saves_and_measures_the_shape(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    summary = run_learn(cli, tmp_path / "run", "tree.sequence.0.explore_touch.max_touches=50",
                        "tree.sequence.1.learn_shape.only_novel=false")  # fmt: skip
    record = summary["learned_shape"]
    assert record["saved"] and record["steps"] == 50
    learned = f"{record['prior_class']}_learned.ply"  # the default name
    assert Path(record["path"]) == tmp_path / "run" / "learned" / learned
    load_mesh(record["path"], size_m=None)  # watertight
    assert 0.0 < record["reconstruction_error_m"] < 0.15
    assert record["poisson_error_m"] > 0.0
    assert summary["touch"]["gpis_contacts"] == len(summary["touch"]["contacts"])
    assert summary["touch"]["kernel_scale_m"] > 0.0


@pytest.mark.slow
def test_touch_learn_skill_saves_a_novel_shape(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    summary = run_learn(cli, tmp_path / "run",
                        f"tree.sequence.1.learn_shape.directory={tmp_path}/lib")  # fmt: skip
    record = summary["learned_shape"]
    assert record["saved"] and record["known"] is False and record["prior_class"] == "chair"
    assert Path(record["path"]).parent == tmp_path / "lib" and Path(record["path"]).is_file()
    assert record["steps"] == summary["touch"]["touches"] > 10
    assert 0.0 < record["reconstruction_error_m"] < 0.06


@pytest.mark.slow
def test_a_learned_shape_is_recognised_and_explored_faster(
    cli: Callable[..., tuple[int, str, str]], tmp_path: Path
) -> None:
    """Paper IV-B4: learn bottle_wide (novel; the PF's best known class is another one), add
    it as a class, touch the same object again: the learned class is the most likely one and
    the exploration ends sooner."""
    common = ["components.probe.with.object=bottle_wide",
              "tree.sequence.1.learn_shape.name=bottle_wide_learned"]  # fmt: skip
    before = run_learn(cli, tmp_path / "before", *common,
                       f"tree.sequence.1.learn_shape.directory={tmp_path}/lib")  # fmt: skip
    learned = before["learned_shape"]["path"]
    assert before["touch"]["mle_class"] != "bottle_wide_learned"
    classes = ", ".join([*KNOWN, learned])
    after = run_learn(cli, tmp_path / "after", *common,
                      f"components.estimator.with.classes=[{classes}]")  # fmt: skip
    print(f"\nbefore: {before['touch']['touches']} touches, MLE {before['touch']['mle_class']}, "
          f"known {before['touch']['known']}, learned {before['learned_shape']}\nafter: "
          f"{after['touch']['touches']} touches, MLE {after['touch']['mle_class']}, "
          f"known {after['touch']['known']}, learned {after['learned_shape']}")
    assert after["touch"]["mle_class"] == "bottle_wide_learned"
    assert after["touch"]["stopped_by"] == "explorer"
    assert after["touch"]["touches"] < before["touch"]["touches"]
    assert after["touch"]["known"] is True and not after["learned_shape"]["saved"]
