"""The training loop (``vistac.plugins.filters.train.fit``): a validation loss that changes only
with the weights, and the step schedule."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from test_training_mirror import _two_link_trajectory
from torch import Tensor, nn
from vistac.plugins.filters import train as train_module


def test_the_validation_loss_changes_only_with_the_weights(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The process model's validation loss (rollouts from disturbed twists, in shuffled
    batches) is the same number each time it is asked with the same weights, however much
    training randomness was drawn in between: the best epoch is chosen by its weights, not by
    its luck. Before, the batches came from the training generator and the loss of unchanged
    weights moved from one epoch to the next."""
    calls: list[Callable[[], float]] = []
    original_fit = train_module.fit

    def spy(parameters: Any, train: Any, val: Callable[[], float], *args: Any) -> Any:
        calls.append(val)
        return original_fit(parameters, train, val, *args)

    monkeypatch.setattr(train_module, "fit", spy)
    windows = {
        "train": [_two_link_trajectory("articulated") for _ in range(8)],
        "val": [_two_link_trajectory("heterogeneous") for _ in range(2)]
        + [_two_link_trajectory("articulated") for _ in range(3)],
    }
    config = train_module.TrainConfig(
        hidden=8, epochs=1, filter_epochs=0, batch_size=2, rollout_steps=3
    )
    rng = np.random.default_rng(0)
    train_module._train_model(
        "gnn", "push", None, windows, config, tmp_path, rng  # type: ignore[arg-type]
    )
    val = calls[0]
    with torch.no_grad():
        first = val()
        rng.random(1000)
        torch.randn(1000)
        assert val() == first


def _schedule(fraction: float, epochs: int) -> list[float]:
    """Adam's step in each epoch of ``fit`` on a toy loss (from its history)."""
    weight = nn.Parameter(torch.ones(1))
    config = train_module.TrainConfig(
        learning_rate=0.01, final_learning_rate_fraction=fraction, patience=epochs
    )

    def train() -> Iterator[Tensor]:
        yield (weight - 3.0).square().sum()

    def val() -> float:
        return float((weight - 3.0).square().sum())

    history = train_module.fit([weight], train, val, [nn.Module()], epochs, config, "toy")
    return [row["learning_rate"] for row in history]


def test_the_step_falls_along_a_half_cosine_to_its_final_fraction() -> None:
    """Known answer: five epochs from 0.01 to 5 % of it take steps 0.01 (1 + cos(pi k / 4)) /
    2 scaled into [0.0005, 0.01]; a fraction of 1 keeps the step constant."""
    got = _schedule(0.05, 5)
    want = [0.0005 + 0.0095 * (1 + math.cos(math.pi * k / 4)) / 2 for k in range(5)]
    np.testing.assert_allclose(got, want, rtol=1e-9)
    np.testing.assert_allclose(_schedule(1.0, 5), [0.01] * 5, rtol=1e-12)
