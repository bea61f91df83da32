"""A look as a position measurement of the belief (``filters.dual`` ``observe_positions``),
which goal pushing uses so that its plans start where the object was seen."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from vistac.plugins.filters.component import position_update
from vistac.plugins.filters.dual import Belief
from vistac.protocols import Scene
from vistac.testing import build_components
from vistac.types import PointCloud, ShapeEstimate, Superquadric


def test_position_update_matches_the_scalar_kalman_update() -> None:
    """Prior var 4e-4 on x, correlated 1e-4 with a parameter of var 1e-2; measure x = 0.01
    with std 0.02: gain 0.5 on x and 0.125 on the parameter."""
    cov = torch.tensor([[4e-4, 1e-4], [1e-4, 1e-2]], dtype=torch.float64)
    belief = Belief(torch.zeros(2, dtype=torch.float64), cov)
    after = position_update(belief, [0], torch.tensor([0.01], dtype=torch.float64), 0.02)
    assert after.mean.tolist() == pytest.approx([0.005, 0.00125])
    assert after.cov[0, 0].item() == pytest.approx(2e-4)
    assert after.cov[1, 1].item() == pytest.approx(1e-2 - 1e-4 * 1e-4 / 8e-4)
    assert torch.allclose(after.cov, after.cov.T)
    assert torch.linalg.eigvalsh(after.cov).min() > 0


def _shape(centres_m: list[tuple[float, float]]) -> ShapeEstimate:
    links = []
    for x_m, y_m in centres_m:
        pose = np.eye(4)
        pose[:3, 3] = [x_m, y_m, 0.025]
        links.append(Superquadric(np.array([0.04, 0.03, 0.025]), np.array([0.1, 0.1]), pose))
    cloud = PointCloud(np.random.default_rng(0).normal([0.0, 0.45, 0.03], 0.02, (200, 3)))
    poses = np.array([[x, y, 0.0] for x, y in centres_m])
    return ShapeEstimate(tuple(links), poses, np.zeros((len(links), 14)), cloud)


def test_observe_positions_moves_matched_links_and_counts_each_fit_once(tmp_path: Path) -> None:
    ctx = build_components(
        {"model": {"plugin": "filters.gnn"}, "filter": {"plugin": "filters.dual"}}, tmp_path
    )
    filter_ = ctx.component("filter")
    first = _shape([(-0.05, 0.45), (0.05, 0.45)])
    filter_.initialise(Scene(first.cloud, first, None))
    std = filter_.belief.cov.diagonal()[filter_.layout.index("x_0")].sqrt().item()
    # The next fit lists the links the other way round, each moved 1 cm in +x.
    moved = _shape([(0.06, 0.45), (-0.04, 0.45)])
    belief = filter_.observe_positions(moved, std)  # measurement as certain as the belief
    x0, x1 = belief.mean[belief.index("x_0")], belief.mean[belief.index("x_1")]
    assert x0 == pytest.approx(-0.045, abs=1e-6) and x1 == pytest.approx(0.055, abs=1e-6)
    assert filter_.observe_positions(moved, std).mean.tolist() == belief.mean.tolist()
    one_link = filter_.observe_positions(_shape([(0.3, 0.3)]), std)  # another link count
    assert one_link.mean.tolist() == belief.mean.tolist()
