"""Tracking accuracy of the dual filter with the analytical model on simulated rect2 pushes.

Slow: records its own pushes with the collection skill, then filters each push with the belief
over the parameters carried from one push to the next (the pose re-set to the true start).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from vistac.cli import main
from vistac.plugins.filters.component import DualFilterComponent, Prior
from vistac.plugins.filters.data import load_trajectories, process_inputs, true_states
from vistac.plugins.filters.dual import Belief
from vistac.plugins.filters.models import load_checkpoint
from vistac.plugins.filters.observation import ObsNoiseNet
from vistac.plugins.filters.state import StateLayout
from vistac.plugins.filters.train import _initial_belief, _projector, _unbatch, observations
from vistac.testing import build_components

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_analytical_filter_tracks_recorded_pushes(tmp_path: Path) -> None:
    torch.set_num_threads(1)
    out = tmp_path / "rect2"
    code = main([
        "-q", "run", str(ROOT / "skills/collect_pushes.yaml"), "--out", str(out), "--overwrite",
        "--set", "components.world.with.object=objects/rect2.yaml",
    ])  # fmt: skip
    assert code == 0
    pushes = load_trajectories([out], kind="push")
    assert pushes
    layout = StateLayout(1)
    model = build_components(
        {"m": {"plugin": "filters.analytical"}}, tmp_path
    ).component("m")
    noise = ObsNoiseNet()  # the shipped noise net, and the filter set up as a skill's
    load_checkpoint(noise, ROOT / "skills/checkpoints/obs_noise_push.pt", "filters.dual", {})
    settings = DualFilterComponent.Config()
    generator = torch.Generator().manual_seed(0)
    rng = np.random.default_rng(0)
    belief: Belief | None = None
    for push in pushes:
        truth = true_states(push, layout)
        projector = _projector(push, rng, splat_px=1)
        observation = settings.observation_model(layout, projector, noise)
        dual = settings.dual_filter(layout, model, observation, float(noise.evidence_steps))
        start = _initial_belief(truth[0], layout, Prior())
        if belief is not None:  # parameters carried over, pose re-set
            mean, cov = start.mean.clone(), start.cov.clone()
            mean[6:], cov[6:, 6:] = belief.mean[6:], belief.cov[6:, 6:]
            start = Belief(mean, cov)
        belief = start
        measured, inputs = observations(push, projector), process_inputs([push])
        nees = []
        with torch.no_grad():
            for step in range(1, push.steps):
                belief = dual.step(
                    belief, _unbatch(inputs[step - 1]), push.dt_s, measured[step], generator
                )
                error = belief.mean[:3] - truth[step, :3]
                nees.append(float(error @ torch.linalg.solve(belief.cov[:3, :3], error)))
        error = belief.mean[:3] - truth[-1, :3]
        assert float(error[:2].norm()) < 0.01, f"{push.source}: position error {error}"
        assert abs(float(error[2])) < 0.15, f"{push.source}: angle error {error}"
        # A consistent filter has a mean NEES of about 3 here; the pixels' noise is not
        # independent, so the visual update is overconfident (measured 3-89 per push with the
        # skill's settings and the cropped images, 101 for one push on another CPU, whose
        # last bits give other recorded pushes; 56-560 with a bare DualFilter, whose pose
        # std has no floor). The bound catches a collapsed covariance (NEES in the
        # thousands), not that known excess.
        assert np.mean(nees) < 200.0, f"{push.source}: overconfident, mean NEES {np.mean(nees)}"
    assert belief is not None
    mass, friction = float(belief.mean[6]), float(belief.mean[7])
    assert mass > 0 and friction > 0
    assert abs(mass * friction - 0.8 * 0.3) < 0.1  # only the product is identifiable
