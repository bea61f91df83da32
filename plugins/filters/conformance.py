"""What the dual filter relies on from a process model, as a check (``vistac.testing``'s
``check_component`` runs it for the kind ``process_model``).

The filter feeds a model C sigma points of a batch of beliefs at once, reads the prediction
without gradients, and treats every point and every batch element as its own: a point's
prediction may depend on that point's state and its element's inputs only. The check puts a
chain of square links in front of a push and a pull and asserts, naming the broken promise:
the shapes and dtype of ``Prediction``, finite values, a non-negative process variance,
untouched states, the same output for the same input, and that predicting a subset of the
points, or one batch element alone, gives their rows of the whole prediction.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout

INTERACTIONS = ("push", "pull")
"""What a process model predicts unless its ``interactions`` says less."""
BATCH = 2
POINTS = 5
DT_S = 1.0 / 15.0
HALF_M = 0.045
GAP_M = 0.004
ROWS_ATOL, ROWS_RTOL = 1e-6, 1e-5
"""How far a point's prediction may move when predicted in another batch (state units and
N, plus this share of the value): the learned models run float32 MLPs without gradients,
whose sums depend on the row count (the shipped GNN's moved by up to 2e-8)."""


def reference_input(n_links: int, link: int, is_pull: float) -> tuple[Tensor, ProcessInput]:
    """Sigma points [BATCH, POINTS, n] around a chain of square links along +x at y = 0.45 m
    (the two batch elements differ), and the input of the gripper 9 mm behind link ``link``'s
    -x side moving along +x (``is_pull`` 1: the same, pulling)."""
    layout = StateLayout(n_links)
    offset = torch.zeros(n_links, 3, dtype=DTYPE)
    offset[:, 0] = torch.arange(n_links, dtype=DTYPE) * (2 * HALF_M + GAP_M)
    pose = torch.zeros(n_links, 6, dtype=DTYPE)
    pose[:, :3] = offset + torch.tensor([0.0, 0.45, 0.0], dtype=DTYPE)
    params = torch.tensor([0.8, 0.3, 0.005, -0.004], dtype=DTYPE).repeat(n_links)
    mean = torch.cat([pose.flatten(), params, torch.full((n_links - 1,), 0.2, dtype=DTYPE)])
    spread = torch.cat([
        torch.tensor([0.002, 0.002, 0.02, 0.002, 0.002, 0.01]).repeat(n_links),
        torch.tensor([0.1, 0.03, 0.003, 0.003]).repeat(n_links),
        torch.full((n_links - 1,), 0.05),
    ]).to(DTYPE)  # fmt: skip
    generator = torch.Generator().manual_seed(n_links)
    noise = torch.randn(BATCH, POINTS, layout.size, generator=generator, dtype=DTYPE)
    states = mean + spread * noise.clamp(-2.0, 2.0)  # masses and frictions stay positive
    start_x_m = float(offset[link, 0]) - HALF_M - 0.009
    tcp = torch.tensor([[start_x_m, 0.46, 0.0, 0.025, 0.0, 0.0],
                        [start_x_m, 0.44, 0.1, 0.02, 0.002, 0.0]], dtype=DTYPE)  # fmt: skip
    inputs = ProcessInput(
        tcp=tcp,
        pd_rad=torch.tensor([0.0, 0.1], dtype=DTYPE),
        is_pull=torch.full((BATCH,), is_pull, dtype=DTYPE),
        link=torch.full((BATCH,), link, dtype=torch.int64),
        link_size_m=torch.full((BATCH, n_links, 2), HALF_M, dtype=DTYPE),
        link_offset=offset.expand(BATCH, n_links, 3).clone(),
    )
    return states, inputs


def check_process_model(model: Any) -> None:
    """Assert the promises above for every link count the model supports (1 and 2 for a
    model of any count, ``n_links`` = None; each of a tuple), each acted link, and each
    interaction it predicts (``interactions``, default push and pull)."""
    n_links = getattr(model, "n_links", "missing")
    counts = n_links if isinstance(n_links, tuple) else (1, 2) if n_links is None else (n_links,)
    assert all(isinstance(n, int) and n >= 1 for n in counts) and counts, (
        f"n_links must be None (any count), a positive int or a tuple of them, got {n_links!r}"
    )
    interactions = getattr(model, "interactions", INTERACTIONS)
    assert interactions and set(interactions) <= set(INTERACTIONS), (
        f"interactions must name some of {INTERACTIONS}, got {interactions!r}"
    )
    for count in counts:
        for link in range(count):
            for kind in interactions:
                _check_case(model, count, link, float(kind == "pull"))


def _check_case(model: Any, n_links: int, link: int, is_pull: float) -> None:
    case = f"{n_links} link(s), acting on link {link}, {'pull' if is_pull else 'push'}"
    states, inputs = reference_input(n_links, link, is_pull)
    before = states.clone()
    with torch.no_grad():
        prediction = model.predict(states, inputs, DT_S)
        _check_prediction(prediction, (BATCH, POINTS), n_links, case)
        assert torch.equal(states, before), f"predict must not change the states ({case})"
        again = model.predict(states, inputs, DT_S)
        for name in ("pose", "force_n", "process_var"):
            assert torch.equal(getattr(prediction, name), getattr(again, name)), (
                f"the same states and inputs must give the same {name} ({case})"
            )
        alone = model.predict(states[1], _element(inputs, 1), DT_S)
        _check_prediction(alone, (POINTS,), n_links, f"{case}, unbatched")
        _check_rows(alone, prediction, (1, slice(None)), f"one batch element alone ({case})")
        subset = model.predict(states[:, :2], inputs, DT_S)
        _check_rows(subset, prediction, (slice(None), slice(0, 2)), f"two of the points ({case})")


def _element(inputs: ProcessInput, index: int) -> ProcessInput:
    """The inputs of one batch element."""
    return inputs.map(lambda tensor: tensor[index])


def _check_prediction(prediction: Any, lead: tuple[int, ...], n_links: int, case: str) -> None:
    assert isinstance(prediction, Prediction), (
        f"predict must return a vistac.plugins.filters.state.Prediction, got "
        f"{type(prediction).__name__} ({case})"
    )
    expected = {"pose": (*lead, 6 * n_links), "force_n": (*lead, 2)}
    for name, shape in expected.items():
        value = getattr(prediction, name)
        assert tuple(value.shape) == shape, (
            f"Prediction.{name}: expected shape {shape}, got {tuple(value.shape)} ({case})"
        )
    var_shapes = {(*lead[:-1], 6 * n_links), (*lead, 6 * n_links)}
    assert tuple(prediction.process_var.shape) in var_shapes, (
        f"Prediction.process_var: expected one of {sorted(var_shapes)}, got "
        f"{tuple(prediction.process_var.shape)} ({case})"
    )
    for name in ("pose", "force_n", "process_var"):
        value = getattr(prediction, name)
        assert value.dtype == DTYPE, (
            f"Prediction.{name} must be float64, got {value.dtype} ({case})"
        )
        assert bool(torch.isfinite(value).all()), f"Prediction.{name} is not finite ({case})"
    assert bool((prediction.process_var >= 0).all()), f"a negative process variance ({case})"


def _check_rows(part: Prediction, whole: Prediction, rows: tuple[Any, ...], what: str) -> None:
    for name in ("pose", "force_n"):
        got, want = getattr(part, name), getattr(whole, name)[rows]
        error = float(((got - want).abs() - ROWS_RTOL * want.abs()).max())
        assert error <= ROWS_ATOL, (
            f"Prediction.{name} of {what} differs from its rows of the whole prediction by "
            f"{error:.3g}: a point's prediction may depend on its own state and inputs only"
        )
