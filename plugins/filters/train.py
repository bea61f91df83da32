"""``vistac train``: collect interactions in simulation and train the learned filter models.

1. Collect: run the collection skill once per training and validation object (or read
   recorded run folders given with ``--data``).
2. Process model (per interaction type and model): open-loop rollouts of ``rollout_steps``
   from the true pose and a disturbed twist (``twist_noise``, see :func:`rollout_errors`),
   loss = Gaussian NLL of the true next pose under the predicted mean and the learned
   process noise + MSE of the mean + NLL of the measured finger force (IV-B2).
   With ``missed_pushes``, each recorded push also goes in moved to miss the object
   (:func:`vistac.plugins.filters.data.missed_push`); with ``replayed_pushes``, each
   also goes in replayed in the simulator with the object's parameters drawn anew
   (:func:`vistac.plugins.filters.information.replayed_pushes`).
3. Observation noise: ObsNoiseNet by the NLL of the measured depth image and force around
   the image projected at the true pose (the observation-noise term of IV-B2).
4. End to end: ``filter_epochs`` passes through the dual filter on windows of a third of a
   trajectory, loss = NLL + MSE of the true state under the belief; gradients reach the
   process model and ObsNoiseNet through the filter.
Validation loss picks the checkpoint and stops training when it stops improving.
Checkpoints are state dicts (``<model>_<interaction>.pt``, ``obs_noise_<interaction>.pt``)
with a JSON sidecar; ``train.json`` reports the losses, the data and the time.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from torch import Tensor, nn
from vistac.errors import ConfigError, DataError, validation_issues
from vistac.objects import interleave_types, link_frames, load_object, write_configurations
from vistac.plugins.filters.component import DualFilterComponent, Prior, prior_belief
from vistac.plugins.filters.data import (
    Trajectory,
    describe,
    load_trajectories,
    mirrored,
    missed_pushes,
    object_cloud,
    process_inputs,
    stack_equal_length,
    true_states,
)
from vistac.plugins.filters.dual import Belief, DualFilter
from vistac.plugins.filters.information import replayed_pushes
from vistac.plugins.filters.models import sidecar_path
from vistac.plugins.filters.nets import RATE_SCALE_RADPS, SPEED_SCALE_MPS
from vistac.plugins.filters.observation import (
    DepthProjector,
    ObsNoiseNet,
    ProjectionObservationModel,
    observation_vector,
)
from vistac.plugins.filters.state import DTYPE, ProcessInput, StateLayout

log = logging.getLogger(__name__)

ModelName = Literal["gnn", "ff"]
Interaction = Literal["push", "pull"]
_POSE_SCALE = torch.tensor([0.01, 0.01, 0.1, 0.01, 0.01, 0.1], dtype=DTYPE)
"""Loss scale of (x, y m, theta rad, vx, vy m/s, omega rad/s)."""
_FORCE_SCALE_N = 1.0
_LOSS_JITTER = 0.01
"""Share of the starting belief's variance added to the belief's in the end-to-end loss (a
floor of a tenth of the prior's std in every entry). The joint's and the fused links'
constraints leave the belief almost no variance across them, which the simulated truth breaks
by a fraction of a millimetre, and with few sigma points the weighted parameter covariance
loses a direction: without the floor, the NLL of each multi-link window was about 1e10 and
drowned everything else."""


class TrainConfig(BaseModel):
    """A training preset (``--preset tiny|paper`` or a YAML file with these fields)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    objects: Literal["shipped", "generated"] = "shipped"
    """shipped: skills/objects/*.yaml; generated: `vistac objects generate` train/val split."""
    shipped_train: tuple[str, ...] = ("rect1", "tri2", "ellip2", "hexagon", "artic_rect_rect")
    shipped_val: tuple[str, ...] = ("rect3", "hetero_rect_tri")
    max_objects: int | None = Field(default=None, gt=0, description="cap on objects per split")
    runs_per_object: int = Field(default=1, gt=0, description="collection-skill runs per object")
    collect_overrides: tuple[str, ...] = ()
    """``--set`` overrides of the collection skill, e.g. "tree.sequence.0.repeat.max=3"."""
    models: tuple[ModelName, ...] = ("gnn", "ff")
    interactions: tuple[Interaction, ...] = ("push", "pull")
    hidden: int = Field(default=64, ge=4)
    rollout_steps: int = Field(
        default=25, gt=0, description="open-loop steps from each true state (a window's length)"
    )
    twist_noise: float = Field(
        default=1.0,
        ge=0.0,
        description="noise on the twist each training rollout starts from, in the nets' "
        "speed scales (see rollout_errors): 0 lets a net carry the twist on and ignore the CoM",
    )
    truth_force_weight: float = Field(
        default=0.0,
        ge=0.0,
        description="weight of the force error one step ahead of each true state (what the "
        "filter's tactile update expects near the truth), next to the rollouts' forces",
    )
    epochs: int = Field(default=30, gt=0)
    noise_epochs: int = Field(default=5, ge=0)
    filter_epochs: int = Field(default=1, ge=0)
    filter_sigma_points: int = Field(default=24, ge=2)
    filter_windows: int | None = Field(
        default=None, gt=0, description="cap on end-to-end windows/epoch"
    )
    batch_size: int = Field(default=16, gt=0)
    learning_rate: float = Field(default=2e-3, gt=0)
    filter_learning_rate: float = Field(
        default=2e-4, gt=0, description="Adam step of the end-to-end epochs (fine-tuning)"
    )
    final_learning_rate_fraction: float = Field(
        default=1.0, gt=0, le=1, description="Adam's step falls along a half cosine to this "
        "fraction of its start over the epochs of each model (1: a constant step)",
    )
    patience: int = Field(
        default=5, gt=0, description="epochs without validation gain before stopping"
    )
    missed_pushes: bool = Field(
        default=True,
        description="also train the process models on each recorded push moved to miss the "
        "object (it stays at rest): they learn that only contact moves it",
    )
    replayed_pushes: int = Field(
        default=0, ge=0,
        description="also train the process models on each recorded push replayed this many "
        "times in the simulator from its start along its path, each time with the object's "
        "parameters drawn anew: the same push on objects that differ only in their parameters "
        "(vistac.plugins.filters.information.replayed_pushes)",
    )  # fmt: skip
    mirror: bool = Field(
        default=False,
        description="train the process models on each window or its mirror image, reflected "
        "across the line of its push (vistac.plugins.filters.data.mirrored), chosen at random "
        "for every batch: planar pushing is mirror-symmetric, so this doubles the scenes the "
        "models learn from at the same cost per epoch; validation stays unreflected",
    )
    seed: int = 0


PRESETS: dict[str, TrainConfig] = {
    "tiny": TrainConfig(
        shipped_train=("rect1",), shipped_val=("rect3",), models=("gnn", "ff"),
        collect_overrides=("tree.sequence.0.repeat.max=6",), hidden=32, epochs=8,
        noise_epochs=2, filter_epochs=1,
        filter_sigma_points=16, filter_windows=4, batch_size=8,
    ),
    "ship": TrainConfig(
        objects="generated", models=("gnn",), hidden=32,
        collect_overrides=("tree.sequence.0.repeat.max=8",), epochs=30, noise_epochs=3,
        filter_epochs=1, filter_sigma_points=16, filter_windows=8, batch_size=16, patience=10,
    ),
    "paper": TrainConfig(
        objects="generated", collect_overrides=("tree.sequence.0.repeat.max=8",), hidden=64,
        epochs=60, noise_epochs=5, filter_epochs=1, filter_sigma_points=24, filter_windows=64,
        patience=8,
    ),
}  # fmt: skip
PRESETS["ship_ff"] = PRESETS["ship"].model_copy(
    update={"models": ("ff",), "interactions": ("push",)}
)
"""The feed-forward baseline (one model per link count) on the ship collection, for the A-FF
column of `vistac eval`: ``--preset ship_ff --data SHIP_OUT/data``."""


def load_preset(name: str) -> TrainConfig:
    """A named preset or a YAML file of TrainConfig fields."""
    if name in PRESETS:
        return PRESETS[name]
    path = Path(name)
    if not path.is_file():
        raise ConfigError(f"unknown preset {name!r}: use {', '.join(PRESETS)} or a YAML file")
    data = preset_file(path)
    data.pop("active", None)  # active-training settings: vistac.plugins.filters.active
    try:
        return TrainConfig.model_validate(data)
    except ValidationError as error:
        raise ConfigError(validation_issues("", error, TrainConfig), str(path)) from None


def preset_file(path: Path) -> dict[str, Any]:
    """The mapping of a preset YAML file; a ConfigError (one line) for a file that is
    malformed or not a mapping."""
    from vistac.skill import read_yaml

    data = read_yaml(path)
    if not isinstance(data, dict):
        raise ConfigError("a preset file is a YAML mapping of training settings", str(path))
    return data


# ---------------------------------------------------------------------------------------------
# Collection


def object_files(config: TrainConfig, skill_dir: Path, out_dir: Path) -> dict[str, list[Path]]:
    """Train and validation object files of the preset."""
    if config.objects == "generated":
        folder = out_dir / "objects"
        split = write_configurations(config.seed, folder)
        files = {k: [folder / f"{name}.yaml" for name in split[k]] for k in ("train", "val")}
    else:
        folder = skill_dir / "objects"
        files = {
            "train": [folder / f"{name}.yaml" for name in config.shipped_train],
            "val": [folder / f"{name}.yaml" for name in config.shipped_val],
        }
    if config.max_objects is None:
        return files
    return {split: interleave_types(paths)[: config.max_objects] for split, paths in files.items()}


def collect(skill: Path, objects: list[Path], out_dir: Path, config: TrainConfig) -> list[Path]:
    """Run the collection skill on every object; returns the folders of the runs that recorded
    an episode (a DataError when none did)."""
    from vistac.cli import main

    runs = []
    for obj in objects:
        load_object(obj)  # a clear error before any simulation
        for run in range(config.runs_per_object):
            run_dir = out_dir / f"{obj.stem}_{run}"
            if not (run_dir / "summary.json").is_file():
                args = ["-q", "run", str(skill), "--out", str(run_dir), "--overwrite",
                        "--seed", str(config.seed + run),
                        "--set", f"components.world.with.object={obj.resolve()}"]  # fmt: skip
                for override in config.collect_overrides:
                    args += ["--set", override]
                if main(args) != 0:
                    log.warning("collection on %s stopped early; see %s", obj.name, run_dir)
            if not any((run_dir / "episodes").glob("*/data.npz")):
                log.warning("%s: no episode recorded, %s skipped", run_dir, obj.name)
                continue
            runs.append(run_dir)
            log.info("collected %s", run_dir)
    if not runs:
        names = ", ".join(obj.stem for obj in objects[:4]) + (", ..." if len(objects) > 4 else "")
        raise DataError(f"collection recorded no episode on {names}; see the runs in {out_dir}")
    return runs


# ---------------------------------------------------------------------------------------------
# Losses


def gaussian_nll(error: Tensor, var: Tensor) -> Tensor:
    """Mean Gaussian negative log-likelihood of errors [..., d] with variances [..., d]."""
    return 0.5 * (error.square() / var + var.log() + math.log(2 * math.pi)).mean()


def rollout_errors(
    model: Any,
    windows: list[Trajectory],
    rollout_steps: int,
    twist_noise: float = 0.0,
    generator: torch.Generator | None = None,
) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """Per step of open-loop rollouts of ``rollout_steps`` from the true state, over a batch of
    B equal-length windows of L links: (pose error [B, 1, 6L] and the process variance
    accumulated since the rollout's start [B, 1, 6L], both in units of ``_POSE_SCALE``; force
    error [B, 2] in ``_FORCE_SCALE_N``). The variance adds up along a rollout as for
    independent steps, so the learned per-step noise stays the one-step noise the filter needs
    while long rollouts make the model answer for the drift its own predictions build up.

    ``twist_noise``: each rollout starts from the true pose but a twist disturbed by Gaussian
    noise of this many times the nets' speed scales (``SPEED_SCALE_MPS``,
    ``RATE_SCALE_RADPS``), drawn with ``generator``. From the true twist a net does well by
    carrying it on (the next omega is the current one) and never learns what turns the object;
    a disturbed start makes it find the twist from the contact and the CoM."""
    layout = StateLayout(windows[0].n_links)
    truth = torch.stack([true_states(w, layout) for w in windows])  # [B, T, n]
    inputs = process_inputs(windows)
    force = torch.as_tensor(np.stack([w.force_n for w in windows]), dtype=DTYPE)
    scale = _POSE_SCALE.repeat(layout.n_links)
    for start in range(0, truth.shape[1] - 1, rollout_steps):
        state = disturb_twist(truth[:, start : start + 1], layout, twist_noise, generator)
        accumulated = torch.zeros((), dtype=DTYPE)
        for step in range(start, min(start + rollout_steps, truth.shape[1] - 1)):
            prediction = model.predict(state, inputs[step], windows[0].dt_s)
            target = truth[:, step + 1, layout.pose_slice].unsqueeze(1)
            error = (prediction.pose - target) / scale
            accumulated = accumulated + prediction.process_var
            var = (accumulated.unsqueeze(-2) / scale**2).expand_as(error)
            yield error, var, (prediction.force_n[:, 0] - force[:, step + 1]) / _FORCE_SCALE_N
            params = state[..., layout.parameter_slice]
            state = torch.cat([prediction.pose, params], -1)


def disturb_twist(
    states: Tensor, layout: StateLayout, noise: float, generator: torch.Generator | None
) -> Tensor:
    """states [B, 1, n] with each link's twist plus noise * the speed scales (a copy)."""
    if noise == 0.0:
        return states
    states = states.clone()
    twist = layout.link_pose(states)[..., 3:]  # a view of the copy: [B, 1, L, 3]
    scale = torch.tensor([SPEED_SCALE_MPS, SPEED_SCALE_MPS, RATE_SCALE_RADPS], dtype=DTYPE)
    twist += noise * scale * torch.randn(twist.shape, generator=generator, dtype=DTYPE)
    return states


def rollout_loss(
    model: Any,
    windows: list[Trajectory],
    rollout_steps: int,
    twist_noise: float = 0.0,
    generator: torch.Generator | None = None,
    truth_force_weight: float = 0.0,
) -> Tensor:
    """Open-loop rollout loss over a batch of equal-length windows of one link count (see
    :func:`rollout_errors` for ``twist_noise``), plus ``truth_force_weight`` times
    ``one_step_force_loss``."""
    losses = [
        gaussian_nll(error, var) + error.square().mean() + force_error.square().mean()
        for error, var, force_error in rollout_errors(
            model, windows, rollout_steps, twist_noise, generator
        )
    ]
    loss = torch.stack(losses).mean()
    if truth_force_weight > 0.0:
        loss = loss + truth_force_weight * one_step_force_loss(model, windows)
    return loss


def _projector(window: Trajectory, rng: np.random.Generator, splat_px: int = 1) -> DepthProjector:
    if window.depth_m is None or window.camera_pose is None or window.intrinsics is None:
        raise DataError(f"{window.source}: no depth frames; collect with record_depth: true")
    points, owners = object_cloud(window.spec, rng)
    height, width = window.depth_m.shape[1:]
    return DepthProjector(
        points, owners, link_frames(window.spec), window.intrinsics, window.camera_pose[0],
        width_px=width, height_px=height, splat_px=splat_px,
    )  # fmt: skip


def observations(window: Trajectory, projector: DepthProjector) -> Tensor:
    """The measured observation vectors [T, H*W + 2] of a window."""
    assert window.depth_m is not None
    return observation_vector(
        torch.as_tensor(window.depth_m, dtype=DTYPE),
        torch.as_tensor(window.force_n, dtype=DTYPE),
        projector.background_m,
    )


def one_step_forces(model: Any, windows: list[Trajectory]) -> Tensor:
    """The process model's finger forces [B, T - 1, 2] one step ahead of the true states
    1 .. T - 1 of B equal-length windows of one link count (every step of every window in one
    batch; with gradients when they are enabled)."""
    layout, steps = StateLayout(windows[0].n_links), windows[0].steps - 1
    truth = torch.stack([true_states(w, layout)[:-1] for w in windows])  # [B, T - 1, n]
    first = process_inputs(windows)[0]
    tcp = torch.as_tensor(np.stack([w.tcp[:-1] for w in windows]), dtype=DTYPE)
    inputs = ProcessInput(
        tcp.flatten(0, 1), first.pd_rad.repeat_interleave(steps),
        first.is_pull.repeat_interleave(steps), first.link.repeat_interleave(steps),
        first.link_size_m.repeat_interleave(steps, 0),
        first.link_offset.repeat_interleave(steps, 0),
    )  # fmt: skip
    force = model.predict(truth.flatten(0, 1)[:, None], inputs, windows[0].dt_s).force_n
    return force[:, 0].unflatten(0, (len(windows), steps))


def predicted_forces(model: Any, window: Trajectory) -> Tensor:
    """The process model's finger forces [T, 2] one step ahead of the window's true states
    (at step 0, the measured force): the tactile expectation of eq. 28."""
    with torch.no_grad():
        ahead = one_step_forces(model, [window])[0]
    return torch.cat([torch.as_tensor(window.force_n[:1], dtype=DTYPE), ahead])


def one_step_force_loss(model: Any, windows: list[Trajectory]) -> Tensor:
    """Mean squared error (in ``_FORCE_SCALE_N``) of the forces one step ahead of the true
    states of equal-length windows: what the filter expects of a sigma point near the truth."""
    measured = torch.as_tensor(np.stack([w.force_n[1:] for w in windows]), dtype=DTYPE)
    return ((one_step_forces(model, windows) - measured) / _FORCE_SCALE_N).square().mean()


def correlation_steps(errors: list[Tensor]) -> float:
    """Integrated autocorrelation time ``1 + 2 sum_k rho_k`` (steps, >= 1) of error sequences
    [T_i, d] about zero (a model's bias that persists through a trajectory counts as
    correlation), the lags summed while the autocorrelation stays positive (Geyer's initial
    positive sequence)."""
    longest = max(len(error) for error in errors)
    numerator, denominator = torch.zeros(longest, dtype=DTYPE), torch.zeros((), dtype=DTYPE)
    for error in errors:
        denominator = denominator + error.square().sum()
        for lag in range(1, len(error)):
            numerator[lag] += (error[lag:] * error[:-lag]).sum()
    rho = numerator[1:] / denominator.clamp_min(1e-300)
    positive = int((rho <= 0).nonzero()[0]) if bool((rho <= 0).any()) else len(rho)
    return float(1.0 + 2.0 * rho[:positive].sum())


def noise_loss(
    noise_net: ObsNoiseNet, window: Trajectory, force_n: Tensor, rng: np.random.Generator
) -> Tensor:
    """NLL of the measured observations around the projection at the true poses and the
    model's forces ``force_n`` [T, 2] (see ``predicted_forces``)."""
    projector = _projector(window, rng)
    measured = observations(window, projector)
    rendered = projector.render(torch.as_tensor(window.poses, dtype=DTYPE)[:, None]).squeeze(1)
    expected = torch.cat([rendered.flatten(-2), force_n], -1)
    return gaussian_nll(measured - expected, noise_net.noise_var(measured))


def filter_loss(
    model: Any,
    noise_net: ObsNoiseNet,
    window: Trajectory,
    config: TrainConfig,
    generator: torch.Generator,
    rng: np.random.Generator,
) -> Tensor:
    """NLL + MSE of the true state under the dual filter's belief along one window."""
    layout = StateLayout(window.n_links)
    truth = true_states(window, layout)
    projector = _projector(window, rng)
    obs_model = DualFilterComponent.Config().observation_model(layout, projector, noise_net)
    filter_ = training_filter(layout, model, obs_model, noise_net, config.filter_sigma_points)
    belief = _initial_belief(truth[0], layout, Prior())
    measured = observations(window, projector)
    inputs = process_inputs([window])
    start_var = belief.cov.diagonal()
    losses = []
    for step in range(1, window.steps):
        belief = filter_.step(
            belief, _unbatch(inputs[step - 1]), window.dt_s, measured[step], generator
        )
        losses.append(belief_loss(truth[step], belief, start_var, layout))
    return torch.stack(losses).mean()


def training_filter(
    layout: StateLayout,
    model: Any,
    obs_model: ProjectionObservationModel,
    noise_net: ObsNoiseNet,
    sigma_points: int,
) -> DualFilter:
    """The dual filter the end-to-end epochs train through: a skill's default ``filters.dual``
    with the noise net's evidence steps; only the number of sigma points is the preset's."""
    settings = DualFilterComponent.Config()
    measured = float(noise_net.evidence_steps)
    return settings.dual_filter(layout, model, obs_model, measured, sigma_points)


def belief_loss(truth: Tensor, belief: Belief, start_var: Tensor, layout: StateLayout) -> Tensor:
    """NLL (per entry) + MSE of the true state [n] under a belief, the pose in units of
    ``_POSE_SCALE``, with ``_LOSS_JITTER`` times the starting variance [n] added to the
    belief's."""
    scale = torch.ones(layout.size, dtype=DTYPE)
    scale[layout.pose_slice] = _POSE_SCALE.repeat(layout.n_links)
    error = (truth - belief.mean) / scale
    cov = (belief.cov + torch.diag(_LOSS_JITTER * start_var)) / (scale[:, None] * scale[None, :])
    nll = 0.5 * (error @ torch.linalg.solve(cov, error) + torch.logdet(cov))
    return nll / layout.size + error.square().mean()


def _unbatch(inputs: Any) -> Any:
    return inputs.map(lambda tensor: tensor[0])


def _initial_belief(truth: Tensor, layout: StateLayout, prior: Any) -> Belief:
    """The belief a run starts from: the true pose and twist, the prior parameters."""
    return prior_belief(layout.link_pose(truth).numpy(), prior, layout)


# ---------------------------------------------------------------------------------------------
# Training loops


def batches(
    windows: list[Trajectory], size: int, rng: np.random.Generator
) -> Iterator[list[Trajectory]]:
    """Shuffled batches of windows that share a link count."""
    by_links: dict[int, list[Trajectory]] = {}
    for window in windows:
        by_links.setdefault(window.n_links, []).append(window)
    chunks = []
    for group in by_links.values():
        order = rng.permutation(len(group))
        chunks += [[group[i] for i in order[s : s + size]] for s in range(0, len(group), size)]
    for index in rng.permutation(len(chunks)):
        yield chunks[index]


def _validation_randomness(config: TrainConfig) -> tuple[np.random.Generator, torch.Generator]:
    """Fresh generators (numpy, torch) from one seed for each validation pass: the batches,
    twist disturbances, clouds and sigma points of the validation loss are the same every
    epoch, so that it changes only with the weights and picks the best epoch for them."""
    return np.random.default_rng(config.seed + 1), torch.Generator().manual_seed(config.seed + 1)


def fit(
    parameters: list[nn.Parameter],
    train_loss: Callable[[], Iterator[Tensor]],
    val_loss: Callable[[], float],
    modules: list[nn.Module],
    epochs: int,
    config: TrainConfig,
    label: str,
    learning_rate: float | None = None,
) -> list[dict[str, float]]:
    """Adam with validation-based early stopping; restores the best weights, which may be the
    starting ones: an epoch that makes the validation loss worse (the end-to-end epochs can)
    never replaces a better model. ``learning_rate``: Adam's step (default the preset's).
    Returns one row per epoch (train, val, learning_rate); the validation loss of the starting
    weights is logged."""
    optimiser = torch.optim.Adam(parameters, lr=learning_rate or config.learning_rate)
    start_lr = optimiser.param_groups[0]["lr"]
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimiser, T_max=max(1, epochs - 1), eta_min=start_lr * config.final_learning_rate_fraction
    )
    with torch.no_grad():
        start = val_loss()
    log.info("%s: validation loss %.4g before training", label, start)
    best = start if math.isfinite(start) else math.inf
    best_state = [copy.deepcopy(m.state_dict()) for m in modules]
    stale, history = 0, []
    for epoch in range(epochs):
        losses = []
        for loss in train_loss():
            optimiser.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(parameters, 10.0)
            optimiser.step()
            losses.append(float(loss.detach()))
        with torch.no_grad():
            val = val_loss()
        lr = optimiser.param_groups[0]["lr"]
        history.append(
            {"epoch": epoch, "train": float(np.mean(losses)), "val": val, "learning_rate": lr}
        )
        schedule.step()
        _progress(label, epoch + 1, epochs, history[-1])
        if val < best - 1e-4:
            best, stale = val, 0
            best_state = [copy.deepcopy(m.state_dict()) for m in modules]
        else:
            stale += 1
            if stale >= config.patience:
                break
    if history and best == start:
        log.warning("%s: no epoch beat the starting weights (val %.4g); kept them", label, start)
    for module, state in zip(modules, best_state, strict=True):
        module.load_state_dict(state)
    return history


def _progress(label: str, done: int, total: int, row: dict[str, float]) -> None:
    width = 20
    bar = "#" * (width * done // total) + "." * (width - width * done // total)
    sys.stderr.write(
        f"\r{label:<18} [{bar}] {done}/{total} train {row['train']:.3f} val {row['val']:.3f}"
    )
    sys.stderr.write("\n" if done == total else "")
    sys.stderr.flush()


def build_model(
    name: ModelName,
    n_links: int,
    config: TrainConfig,
    out_dir: Path,
    checkpoint: Path | None = None,
) -> Any:
    """A process model of the preset's architecture: fresh (seeded) or from ``checkpoint``."""
    from vistac.testing import build_components

    options: dict[str, Any] = {"hidden": config.hidden}
    if name == "ff":
        options["n_links"] = n_links
    if checkpoint is not None:
        options["checkpoint"] = str(checkpoint.resolve())
    spec = {"model": {"plugin": f"filters.{name}", "with": options}}
    return build_components(spec, out_dir / ".build", seed=config.seed).component("model")


def train_interaction(
    kind: Interaction,
    data: dict[str, list[Trajectory]],
    config: TrainConfig,
    out_dir: Path,
    warm_start: bool = False,
) -> dict[str, Any]:
    """Train every model of the preset plus ObsNoiseNet on one interaction type.

    ``warm_start``: continue from the checkpoints already in ``out_dir`` (where there are
    some) instead of fresh weights, as each round of active training does.
    """
    windows = {
        split: stack_equal_length([t for t in trajs if t.kind == kind], window_steps(trajs))
        for split, trajs in data.items()
    }
    if config.missed_pushes and kind == "push":
        windows["missed"] = stack_equal_length(
            missed_pushes(data["train"]), window_steps(data["train"])
        )
    if config.replayed_pushes and kind == "push":
        replayed = replayed_pushes(data["train"], config.replayed_pushes,
                                   np.random.default_rng([config.seed, 1]))  # fmt: skip
        windows["replayed"] = stack_equal_length(replayed, window_steps(data["train"]))
    _check_windows(kind, windows, config)
    rng = np.random.default_rng(config.seed)
    report: dict[str, Any] = {"windows": {k: len(v) for k, v in windows.items()}}
    noise_net = ObsNoiseNet().to(DTYPE)
    noise_path = out_dir / f"obs_noise_{kind}.pt"
    if warm_start and noise_path.is_file():
        noise_net.load_state_dict(torch.load(noise_path, weights_only=True))

    def train_noise(model: Any) -> None:
        """The noise net learns the first model's force error (the tactile expectation) and
        how many steps that error persists, on the objects that model takes (an FF: those
        of its link count)."""
        if "obs_noise" in report:
            return
        links = getattr(model, "n_links", None)
        own = windows if links is None else _only(windows, links)
        report["obs_noise"] = _train_noise(noise_net, own, model, config, rng)
        val = [w for w in data["val"] if w.kind == kind and links in (None, w.n_links)]
        errors = [predicted_forces(model, w) - torch.as_tensor(w.force_n, dtype=DTYPE)
                  for w in val]  # fmt: skip
        noise_net.evidence_steps.fill_(correlation_steps(errors))
        report["evidence_steps"] = float(noise_net.evidence_steps)

    for name in config.models:
        report[name] = _train_model(
            name, kind, noise_net, windows, config, out_dir, rng, warm_start, train_noise
        )
    _save_noise(noise_net, noise_path)
    return report


def _check_windows(
    kind: Interaction, windows: dict[str, list[Trajectory]], config: TrainConfig
) -> None:
    """DataError unless there are train and validation windows of ``kind`` and, for the
    feed-forward models (one per link count), validation windows of each training link count
    (without them the FF would be saved untrained: no epoch could beat its start)."""
    if not windows["train"] or not windows["val"]:
        raise DataError(
            f"no {kind} trajectories in the train or validation data; collect some, or train "
            f"only the others with a preset file's interactions: (without {kind})"
        )
    if "ff" not in config.models:
        return
    val_counts = {w.n_links for w in windows["val"]}
    missing = sorted({w.n_links for w in windows["train"]} - val_counts)
    if missing:
        raise DataError(
            f"the validation data has no {kind} trajectories of {missing} links, which the "
            f"feed-forward model of each link count needs; add validation objects with that "
            "many links (a preset's shipped_val or val split) or leave ff out of models"
        )


def window_steps(trajectories: list[Trajectory]) -> int:
    """A third of the typical trajectory (paper 1, IV-B2), at least 3 steps."""
    return max(3, int(np.median([t.steps for t in trajectories])) // 3) if trajectories else 3


def _train_noise(
    noise_net: ObsNoiseNet,
    windows: dict[str, list[Trajectory]],
    model: Any,
    config: TrainConfig,
    rng: np.random.Generator,
) -> list[dict[str, float]]:
    forces = {split: [predicted_forces(model, w) for w in windows[split]]
              for split in ("train", "val")}  # fmt: skip

    def train() -> Iterator[Tensor]:
        for index in rng.permutation(len(windows["train"])):
            yield noise_loss(noise_net, windows["train"][index], forces["train"][index], rng)

    def val() -> float:
        fixed, _ = _validation_randomness(config)
        pairs = zip(windows["val"], forces["val"], strict=True)
        return float(np.mean([float(noise_loss(noise_net, w, f, fixed)) for w, f in pairs]))

    params = list(noise_net.parameters())
    return fit(params, train, val, [noise_net], config.noise_epochs, config, "obs noise")


def _train_model(
    name: ModelName,
    kind: Interaction,
    noise_net: ObsNoiseNet,
    windows: dict[str, list[Trajectory]],
    config: TrainConfig,
    out_dir: Path,
    rng: np.random.Generator,
    warm_start: bool = False,
    before_filter: Callable[[Any], None] = lambda model: None,
) -> dict[str, Any]:
    """Fit one process model by rollouts, call ``before_filter`` with it, then train it end to
    end through the filter and save it."""
    link_counts = sorted({w.n_links for w in windows["train"]})
    if name == "ff" and len(link_counts) > 1:
        # The feed-forward baseline has a fixed link count: one model per count.
        return {
            f"{n}_links": _train_model(name, kind, noise_net, _only(windows, n), config,
                                       out_dir / f"ff{n}", rng, warm_start, before_filter)
            for n in link_counts
        }  # fmt: skip
    path = out_dir / f"{name}_{kind}.pt"
    start = path if warm_start and path.is_file() else None
    model = build_model(name, link_counts[0], config, out_dir, start)
    start_s = time.perf_counter()

    generator = torch.Generator().manual_seed(config.seed)

    def train() -> Iterator[Tensor]:
        extra = windows.get("missed", []) + windows.get("replayed", [])
        for batch in batches(windows["train"] + extra, config.batch_size, rng):
            if config.mirror:
                batch = [mirrored(w) if flip else w for w, flip in zip(
                    batch, rng.random(len(batch)) < 0.5, strict=True)]  # fmt: skip
            yield rollout_loss(model, batch, config.rollout_steps, config.twist_noise, generator,
                               config.truth_force_weight)

    def val() -> float:
        order, fixed = _validation_randomness(config)
        losses = [float(rollout_loss(model, b, config.rollout_steps, config.twist_noise, fixed,
                                     config.truth_force_weight))
                  for b in batches(windows["val"], config.batch_size, order)]  # fmt: skip
        return float(np.mean(losses)) if losses else math.inf

    params = list(model.net.parameters())
    history = fit(params, train, val, [model.net], config.epochs, config, f"{name} {kind}")
    before_filter(model)
    filter_history = _train_filter(model, noise_net, windows, config, rng, f"{name} {kind} DF")
    model.save_checkpoint(path)
    return {
        "checkpoint": str(path), "history": history, "filter_history": filter_history,
        "time_s": time.perf_counter() - start_s,
        "parameters": sum(p.numel() for p in params),
    }  # fmt: skip


def _only(windows: dict[str, list[Trajectory]], n_links: int) -> dict[str, list[Trajectory]]:
    return {k: [w for w in v if w.n_links == n_links] for k, v in windows.items()}


def _train_filter(
    model: Any,
    noise_net: ObsNoiseNet,
    windows: dict[str, list[Trajectory]],
    config: TrainConfig,
    rng: np.random.Generator,
    label: str,
) -> list[dict[str, float]]:
    if config.filter_epochs == 0:
        return []
    generator = torch.Generator().manual_seed(config.seed)

    def loss(window: Trajectory) -> Tensor:
        return filter_loss(model, noise_net, window, config, generator, rng)

    cap = config.filter_windows

    def train() -> Iterator[Tensor]:
        for index in rng.permutation(len(windows["train"]))[:cap]:
            yield loss(windows["train"][index])

    def val() -> float:
        fixed, points = _validation_randomness(config)
        losses = [filter_loss(model, noise_net, w, config, points, fixed)
                  for w in windows["val"][:cap]]  # fmt: skip
        return float(np.mean([float(value) for value in losses]))

    params = list(model.net.parameters()) + list(noise_net.parameters())
    return fit(
        params, train, val, [model.net, noise_net], config.filter_epochs, config, label,
        config.filter_learning_rate,
    )  # fmt: skip


def _save_noise(noise_net: ObsNoiseNet, path: Path) -> None:
    torch.save(noise_net.state_dict(), path)
    sidecar = {"model": "filters.dual", "architecture": {}}
    sidecar_path(path).write_text(json.dumps(sidecar, indent=2), encoding="utf-8")


def recorded_data(data_dirs: list[Path]) -> dict[str, list[Trajectory]]:
    """Train and validation trajectories from ``--data``: the ``data`` folders of earlier
    trainings (their ``train/`` and ``val/`` run folders, the split kept), or run folders
    (the first eighth of their trajectories validates)."""
    absent = [str(folder) for folder in data_dirs if not folder.is_dir()]
    if absent:
        raise ConfigError(f"--data: no such folder {', '.join(absent)}; check the path")
    collections = [folder for folder in data_dirs if (folder / "train").is_dir()]
    if collections and len(collections) < len(data_dirs):
        raise ConfigError(
            "--data: give either the data/ folders of earlier trainings (with train/ and val/) "
            "or recorded run folders, not both"
        )
    if collections:
        missing = [str(folder / "val") for folder in collections if not (folder / "val").is_dir()]
        if missing:
            raise ConfigError(f"--data: no validation runs in {', '.join(missing)}")

        def runs(split: str) -> list[Path]:
            found = (run for folder in collections for run in (folder / split).iterdir())
            return sorted(run for run in found if run.is_dir())

        return {split: load_trajectories(runs(split)) for split in ("train", "val")}
    trajectories = load_trajectories(data_dirs)
    cut = max(1, len(trajectories) // 8)
    return {"train": trajectories[cut:], "val": trajectories[:cut]}


def train(
    skill: Path, out_dir: Path, config: TrainConfig, data_dirs: list[Path] | None = None
) -> dict[str, Any]:
    """Collect (unless ``data_dirs``) and train; writes checkpoints and ``train.json``."""
    start_s = time.perf_counter()
    torch.manual_seed(config.seed)
    data = recorded_data(data_dirs) if data_dirs else None  # bad --data: no out_dir made
    if data is None:
        out_dir.mkdir(parents=True, exist_ok=True)
        files = object_files(config, skill.parent, out_dir)
        data = {
            split: load_trajectories(collect(skill, paths, out_dir / "data" / split, config))
            for split, paths in files.items()
        }
    for kind in config.interactions:  # every interaction's data checked before any training
        _check_windows(kind, {split: [t for t in trajs if t.kind == kind]
                              for split, trajs in data.items()}, config)  # fmt: skip
    out_dir.mkdir(parents=True, exist_ok=True)
    collect_s = time.perf_counter() - start_s
    report: dict[str, Any] = {
        "preset": config.model_dump(mode="json"),
        "data": {split: describe(trajs) for split, trajs in data.items()},
        "collect_time_s": collect_s,
    }
    for kind in config.interactions:
        report[kind] = train_interaction(kind, data, config, out_dir)
    report["time_s"] = time.perf_counter() - start_s
    (out_dir / "train.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    return report
