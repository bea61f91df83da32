"""Action selection and planning speed: ``actions.info_gain`` choosing among 32 candidates, and
one planning step of ``actions.icem``.

Targets (issue: action selection), torch on one thread, the shipped GNN push checkpoint
(hidden 32), a two-link object:

- info gain: < 200 ms per choice with a 2.5 s horizon at 15 Hz (38 prediction steps of all 32
  candidates in one batch), C = 100 sigma points in the filter, 32 in the look-ahead. Peer in
  the same run: the same choice by ``actions.random`` (no prediction).
- iCEM: < 100 ms per planning step with the controller of skills/goal_push.yaml (horizon 2
  pushes, the plugin's default population, elites and iterations). Peer in the same run: plain
  CEM, the same plugin without iCEM's refinements (white noise, a constant population, no
  elites kept, no momentum).
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch
from common import Row, median_time_s
from vistac.testing import build_components, two_box_scene

ROOT = Path(__file__).resolve().parents[1]
CANDIDATES = 32
HORIZON_S = 2.5
RATE_HZ = 15.0
"""The info-gain look-ahead's rate (the plugin's default, the skills' control rate)."""
TARGET_S = 0.2
PLANNING_TARGET_S = 0.1
GOAL = np.array([0.06, 0.50, 0.0])
"""goal_push's goal: link 0 at (0.06, 0.50) m, not turned."""
ICEM = {"horizon_pushes": 2, "angle_weight_m_per_rad": 0.0}
"""The controller settings of skills/goal_push.yaml; the rest are the plugin's defaults."""
PLAIN_CEM = {
    **ICEM,
    "noise_beta": 0.0,
    "noise_scaling": "spectrum",
    "population_decay": 1.0,
    "keep_elites": 0.0,
    "momentum": 0.0,
}
"""The peer: the same controller without iCEM's colored noise (Gaussian samples instead),
population decay, kept elites and momentum."""



def _components(**extra: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """The GNN process model and the dual filter, plus ``extra`` components."""
    checkpoint = str(ROOT / "skills/checkpoints/gnn_push.pt")
    return {
        "model": {"plugin": "filters.gnn", "with": {"checkpoint": checkpoint, "hidden": 32}},
        "filter": {"plugin": "filters.dual", "with": {"sigma_points": 100}},
        **extra,
    }


def time_selection_s(repeats: int) -> tuple[float, float, int]:
    """(info-gain choice, random choice) median seconds, and the candidate count."""
    components = _components(
        affordances={"plugin": "actions.affordances", "with": {"samples": 4 * CANDIDATES}},
        planner={"plugin": "actions.info_gain", "with": {"horizon_s": HORIZON_S}},
        random={"plugin": "actions.random"},
    )
    with tempfile.TemporaryDirectory() as tmp:
        ctx = build_components(components, Path(tmp))
        scene = two_box_scene()
        ctx.component("filter").initialise(scene)
        rng = np.random.default_rng(0)
        candidates = ctx.component("affordances").sample(scene, rng)[:CANDIDATES]
        planner, random = ctx.component("planner"), ctx.component("random")
        active_s = median_time_s(lambda: planner.select(candidates, scene, rng), repeats)
        random_s = median_time_s(lambda: random.select(candidates, scene, rng), repeats)
    return active_s, random_s, len(candidates)


def time_planning_s(repeats: int) -> tuple[float, float, str]:
    """(iCEM step, plain CEM step) median seconds, and the iCEM settings in words.

    Every step after the first starts from the elites the step before kept, as in the skill.
    """
    components = _components(
        icem={"plugin": "actions.icem", "with": ICEM},
        cem={"plugin": "actions.icem", "with": PLAIN_CEM},
    )
    with tempfile.TemporaryDirectory() as tmp:
        ctx = build_components(components, Path(tmp))
        scene = two_box_scene()
        ctx.component("filter").initialise(scene)
        rng = np.random.default_rng(0)
        icem, cem = ctx.component("icem"), ctx.component("cem")
        icem_s = median_time_s(lambda: icem.plan(scene, GOAL, rng), repeats)
        cem_s = median_time_s(lambda: cem.plan(scene, GOAL, rng), repeats)
        config = icem.config
    settings = (
        f"population {config.population}, {config.elites} elites, {config.iterations} "
        f"iterations, horizon {config.horizon_pushes} pushes, look-ahead at {config.rate_hz:g} Hz"
    )
    return icem_s, cem_s, settings


def run(repeats: int) -> list[Row]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        active_s, random_s, count = time_selection_s(repeats)
        icem_s, cem_s, settings = time_planning_s(repeats)
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
            note=f"torch threads = 1; {round(HORIZON_S * RATE_HZ)} batched prediction steps",
        ),
        Row(
            name="iCEM planning step, goal_push controller (GNN 32, L=2)",
            value=icem_s * 1e3,
            unit="ms",
            target=f"< {PLANNING_TARGET_S * 1e3:.0f} ms",
            passed=icem_s < PLANNING_TARGET_S,
            peer="plain CEM: Gaussian white noise, constant population, no kept elites, "
            "no momentum",
            peer_value=cem_s * 1e3,
            note=f"torch threads = 1; {settings}",
        ),
    ]


if __name__ == "__main__":
    for row in run(10):
        print(row)
