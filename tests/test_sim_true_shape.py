"""``sim.true_shape``: superquadrics fitted to the simulated object's true link surfaces, and
the model frames the dual filter puts on them match the frames the process models were
trained in."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import SKILLS
from vistac.errors import ConfigError, DataError
from vistac.objects import link_frames
from vistac.pluginmanager import Plugins
from vistac.plugins.filters.component import ModelFrames
from vistac.plugins.filters.data import link_geometry
from vistac.testing import BOX_POSE, build_components, check_component
from vistac.types import PointCloud

CLOUD = PointCloud(np.array([[0.0, 0.45, 0.03], [0.01, 0.45, 0.001]]))


def _true_shape(plugins: Plugins, tmp_path: Path, obj: Path) -> tuple[object, object]:
    ctx = build_components(
        {"world": {"plugin": "sim.mujoco", "with": {"object": str(obj)}},
         "shape": {"plugin": "sim.true_shape"}},
        tmp_path / "run", plugins=plugins,
    )  # fmt: skip
    return ctx.component("shape"), ctx.component("world")


def test_true_shape_conforms(plugins: Plugins, tmp_path: Path) -> None:
    """A box at the shape-estimator check's reference pose."""
    obj = tmp_path / "box.yaml"
    obj.write_text(yaml.safe_dump({
        "name": "box", "type": "homogeneous", "pose": list(BOX_POSE),
        "links": [{"footprint": "rect1", "height_m": 0.05, "mass_kg": 0.5, "friction": 0.3}],
    }))  # fmt: skip
    shape, _ = _true_shape(plugins, tmp_path, obj)
    check_component(shape)


@pytest.mark.parametrize("name", ["hetero_rect_tri", "artic_rect_rect"])
def test_trained_frames_of_the_true_shape_are_the_training_frames(
    name: str, plugins: Plugins, tmp_path: Path
) -> None:
    """The fitted links' model frames stand where the training's link frames stand (the
    footprint centroids), turned as they are (whatever axes the fit gave each link), and
    their half extents are the training's (up to 10 mm short on a triangle: the fit rounds
    off its tips)."""
    shape, world = _true_shape(plugins, tmp_path, SKILLS / "objects" / f"{name}.yaml")
    estimate = shape.fit(CLOUD)
    frames = ModelFrames.of(estimate, "trained")
    true_poses = link_frames(world.spec)
    half_m, _ = link_geometry(world.spec)
    assert len(frames.poses) == 2
    np.testing.assert_allclose(frames.poses[:, :2], true_poses[:, :2], atol=2e-3)
    turn = np.angle(np.exp(1j * (frames.poses[:, 2] - true_poses[:, 2])))
    np.testing.assert_allclose(turn, 0.0, atol=np.radians(1.0))
    np.testing.assert_allclose(frames.half_extents_m, half_m, atol=0.011)
    np.testing.assert_allclose(frames.box_poses(frames.poses), estimate.initial_poses, atol=1e-9)


def test_true_shape_needs_the_simulated_world(plugins: Plugins, tmp_path: Path) -> None:
    ctx = build_components({"shape": {"plugin": "sim.true_shape"}}, tmp_path, plugins=plugins)
    with pytest.raises(ConfigError, match=r"sim\.mujoco"):
        ctx.component("shape").fit(CLOUD)


def test_true_shape_needs_observed_object_points(plugins: Plugins, tmp_path: Path) -> None:
    """The filter's depth observation needs what the camera saw: a table-only cloud is an
    error naming the camera."""
    shape, _ = _true_shape(plugins, tmp_path, SKILLS / "objects" / "rect1.yaml")
    with pytest.raises(DataError, match="camera"):
        shape.fit(PointCloud(np.array([[0.0, 0.45, 0.0]])))
