"""Active action selection speed: ``actions.info_gain`` choosing among 32 candidates.

Target (issue: action selection): < 200 ms per choice with a 2.5 s horizon at 15 Hz (37
prediction steps of all 32 candidates in one batch), the shipped GNN push checkpoint (hidden
32), C = 100 sigma points, a two-link object, torch on one thread. Peer in the same run: the
same choice by ``actions.random`` (no prediction).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import torch
from common import Row, median_time_s
from vistac.protocols import Scene
from vistac.testing import build_components
from vistac.types import PointCloud, ShapeEstimate, Superquadric

ROOT = Path(__file__).resolve().parents[1]
CANDIDATES = 32
HORIZON_S = 2.5
TARGET_S = 0.2


def _scene() -> Scene:
    """Two 100 x 80 x 50 mm boxes side by side at y = 0.45 m."""
    links = []
    for x_m in (-0.05, 0.05):
        pose = np.eye(4)
        pose[:3, 3] = [x_m, 0.45, 0.025]
        links.append(Superquadric(np.array([0.05, 0.04, 0.025]), np.array([0.1, 0.1]), pose))
    cloud = PointCloud(np.random.default_rng(0).normal([0.0, 0.45, 0.03], 0.02, (500, 3)))
    poses = np.array([[-0.05, 0.45, 0.0], [0.05, 0.45, 0.0]])
    return Scene(cloud, ShapeEstimate(tuple(links), poses, np.zeros((2, 14)), cloud))


def _components() -> dict[str, dict[str, object]]:
    checkpoint = str(ROOT / "skills/checkpoints/gnn_push.pt")
    return {
        "model": {"plugin": "filters.gnn", "with": {"checkpoint": checkpoint, "hidden": 32}},
        "filter": {"plugin": "filters.dual", "with": {"sigma_points": 100}},
        "affordances": {"plugin": "actions.affordances", "with": {"samples": 2 * CANDIDATES}},
        "planner": {"plugin": "actions.info_gain", "with": {"horizon_s": HORIZON_S}},
        "random": {"plugin": "actions.random"},
    }


def time_selection_s(repeats: int) -> tuple[float, float, int]:
    """(info-gain choice, random choice) median seconds, and the candidate count."""
    with tempfile.TemporaryDirectory() as tmp:
        ctx = build_components(_components(), Path(tmp))
        scene = _scene()
        ctx.component("filter").initialise(scene)
        rng = np.random.default_rng(0)
        candidates = ctx.component("affordances").sample(scene, rng)[:CANDIDATES]
        planner, random = ctx.component("planner"), ctx.component("random")
        active_s = median_time_s(lambda: planner.select(candidates, scene, rng), repeats)
        random_s = median_time_s(lambda: random.select(candidates, scene, rng), repeats)
    return active_s, random_s, len(candidates)


def run(repeats: int) -> list[Row]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        active_s, random_s, count = time_selection_s(repeats)
    finally:
        torch.set_num_threads(threads)
    return [
        Row(
            name=f"info-gain choice among {count} candidates (2.5 s, GNN 32, look-ahead C=32, L=2)",
            value=active_s * 1e3,
            unit="ms",
            target=f"< {TARGET_S * 1e3:.0f} ms",
            passed=active_s < TARGET_S,
            peer="actions.random, same candidates",
            peer_value=random_s * 1e3,
            note="torch threads = 1; 37 batched prediction steps",
        )
    ]


if __name__ == "__main__":
    for row in run(10):
        print(row)
