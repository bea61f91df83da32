"""Process-model components of the dual filter: ``filters.gnn``, ``filters.ff`` and
``filters.analytical`` (kind ``process_model``).

The learned models hold their ``nn.Module`` in ``.net``. A checkpoint is the module's state
dict (``torch.save``) plus a JSON sidecar ``<checkpoint>.json`` with the architecture
hyper-parameters; loading checks both against the configuration and names what differs.
"""

from __future__ import annotations

import copy
import functools
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal

import torch
from pydantic import Field, model_validator
from torch import Tensor, nn
from vistac.component import Component, ComponentConfig, ComponentContext, SkillPath
from vistac.errors import ConfigError, ConfigIssue, DataError
from vistac.plugins.filters.analytical import Pressure, PushSettings, analytical_prediction
from vistac.plugins.filters.chain import chain_step
from vistac.plugins.filters.mirror import mirror_averaged
from vistac.plugins.filters.nets import (
    MLP,
    FeedForwardByLinks,
    FeedForwardProcessNet,
    GraphProcessNet,
    layout_of,
)
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput

log = logging.getLogger(__name__)

FF_MAX_LINKS = 8
"""The most links a ``filters.ff`` net takes."""

_TRAIN_HINT = (
    "train one with `vistac train`, or leave `checkpoint` empty for a freshly initialised net"
)
_MAX_LISTED = 5


def sidecar_path(checkpoint: Path) -> Path:
    """The JSON file next to a checkpoint that records its architecture."""
    return checkpoint.with_name(checkpoint.name + ".json")


def _listed(items: list[str]) -> str:
    more = f" (+{len(items) - _MAX_LISTED} more)" if len(items) > _MAX_LISTED else ""
    return ", ".join(items[:_MAX_LISTED]) + more


def _shape(value: Any) -> tuple[int, ...] | str:
    """A tensor's shape, or the type name of anything else."""
    return tuple(value.shape) if isinstance(value, Tensor) else type(value).__name__


def _state_dict_mismatch(expected: dict[str, Tensor], loaded: dict[str, Any]) -> list[str]:
    """What keeps ``loaded`` from fitting a module whose state dict is ``expected``."""
    problems = []
    missing = [key for key in expected if key not in loaded]
    unexpected = [key for key in loaded if key not in expected]
    wrong = [
        f"{key} {_shape(loaded[key])} (expected {tuple(value.shape)})"
        for key, value in expected.items()
        if key in loaded and _shape(loaded[key]) != tuple(value.shape)
    ]
    for label, items in (("missing", missing), ("unexpected", unexpected), ("shape", wrong)):
        if items:
            problems.append(f"{label}: {_listed(items)}")
    return problems


def _check_sidecar(path: Path, plugin: str, architecture: dict[str, int]) -> None:
    sidecar = sidecar_path(path)
    if not sidecar.is_file():
        log.warning("%s has no sidecar %s; checking the weights' shapes only", path, sidecar)
        return
    try:
        saved = json.loads(sidecar.read_text(encoding="utf-8"))
        saved_plugin, saved_architecture = saved["model"], saved["architecture"]
        if not isinstance(saved_architecture, dict):
            raise TypeError(f"architecture is {saved_architecture!r}, not an object")
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise DataError(f"{sidecar}: unreadable checkpoint sidecar ({error})") from None
    if saved_plugin != plugin:
        raise DataError(
            f"{path} was saved by {saved_plugin!r}, not {plugin!r}; use it with that model "
            f"or {_TRAIN_HINT}"
        )
    differing = [
        f"{key}: saved {saved_architecture.get(key)!r}, configured {value!r}"
        for key, value in architecture.items()
        if saved_architecture.get(key) != value
    ]
    if differing:
        raise DataError(
            f"{path} does not match the configured architecture ({'; '.join(differing)}); "
            f"set the saved values in the skill, or {_TRAIN_HINT}"
        )


def load_checkpoint(net: nn.Module, path: Path, plugin: str, architecture: dict[str, int]) -> None:
    """Load the state dict at ``path`` into ``net`` after checking file, sidecar and shapes.

    Raises ConfigError for a missing file, DataError for an unreadable file or one that does
    not fit the architecture; each message names the file and how to fix it.
    """
    if not path.is_file():
        raise ConfigError([ConfigIssue("checkpoint", f"no such file {path}; {_TRAIN_HINT}")])
    _check_sidecar(path, plugin, architecture)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a damaged file
        raise DataError(
            f"{path} is not a readable torch state dict ({type(error).__name__}: "
            f"{str(error).splitlines()[0] if str(error) else ''}); {_TRAIN_HINT}"
        ) from None
    if not isinstance(state, dict):
        raise DataError(f"{path} holds a {type(state).__name__}, not a state dict; {_TRAIN_HINT}")
    problems = _state_dict_mismatch(net.state_dict(), state)
    if problems:
        raise DataError(
            f"{path} does not fit {plugin} with {architecture} ({'; '.join(problems)}); "
            f"check `hidden`/`n_links` in the skill (a checkpoint saved by an older vistac, "
            f"whose net inputs differ, must be retrained), or {_TRAIN_HINT}"
        )
    net.load_state_dict(state)
    log.info("loaded %s weights from %s", plugin, path)


class _LookAheadCopy:
    """A copy of a net for look-aheads, its MLPs in float32 (the learned process noise stays
    float64), with the weights it was made from."""

    def __init__(self, net: nn.Module) -> None:
        with torch.inference_mode(False), torch.no_grad():  # normal tensors in any mode
            self.source = [weight.detach().clone() for weight in _weights(net)]
            self.net = copy.deepcopy(net).requires_grad_(False)
            for module in self.net.modules():
                if isinstance(module, MLP):
                    module.float()
                    module.freeze()

    def matches(self, net: nn.Module) -> bool:
        """Whether ``net`` still has the weights this copy was made from (exactly)."""
        weights = _weights(net)
        return len(weights) == len(self.source) and all(
            torch.equal(weight, source) for weight, source in zip(weights, self.source, strict=True)
        )


def _weights(net: nn.Module) -> list[Tensor]:
    """Every parameter and buffer of ``net``."""
    return [*net.parameters(), *net.buffers()]


class LearnedModelConfig(ComponentConfig):
    """The options of every learned process model."""

    checkpoint: SkillPath | None = None
    """State dict from ``save_checkpoint``; None = fresh weights seeded by the skill."""
    hidden: int = Field(default=64, ge=4, le=1024)
    mirror_average: bool = Field(
        False, description="average each prediction with the reflected prediction of the scene "
        "reflected about the push line (vistac.plugins.filters.mirror): mirror-symmetric "
        "predictions, at the cost of a batch twice as large",
    )


class _LearnedProcessModel(Component):
    """Shared behaviour of the learned process models: seeded construction, checkpoints,
    float32 look-aheads."""

    kind = "process_model"
    plugin: ClassVar[str]
    n_links: int | tuple[int, ...] | None
    net: nn.Module
    _look_ahead_options: ClassVar[dict[str, Any]] = {}
    """Keyword arguments of the net's forward in look-aheads."""

    def __init__(self, config: Any, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(ctx.seed)
            self.net = self._build()
        if config.checkpoint is not None:
            load_checkpoint(self.net, Path(config.checkpoint), self.plugin, self.architecture())
        self._copy: _LookAheadCopy | None = None

    def _build(self) -> nn.Module:
        raise NotImplementedError

    def architecture(self) -> dict[str, int]:
        """The hyper-parameters a checkpoint must match."""
        raise NotImplementedError

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states [..., C, n] -> Prediction (see ``vistac.plugins.filters.state``). Without
        gradients (a filter in a skill) the net's MLPs run in float32 as in ``look_ahead``,
        the finger force included; with them (training) in float64."""
        net = self.net if torch.is_grad_enabled() else self._float32_net()
        if self.config.mirror_average:
            return mirror_averaged(net, states, inputs, dt_s)
        prediction: Prediction = net(states, inputs, dt_s)
        return prediction

    def _float32_net(self) -> nn.Module:
        """The net with its MLPs in float32, copied again whenever the net's weights have
        changed since the last copy (a checkpoint loaded, a training step; compared
        exactly, so any change counts)."""
        if self._copy is None or not self._copy.matches(self.net):
            self._copy = _LookAheadCopy(self.net)
            log.debug("%s: float32 copy of the net made", self.plugin)
        return self._copy.net

    def look_ahead(self) -> Callable[[Tensor, ProcessInput, float], Prediction]:
        """The prediction for one look-ahead (no gradients, the finger force not needed):
        the net with its MLPs in float32, about twice as fast on CPU. The features, the
        integration of the predicted change and the process noise stay float64, and so does
        the Prediction (poses within 1e-9 m and 1e-7 rad of the float64 net's after 37
        steps, see tests/test_lookahead_float32.py).

        The copy is that of ``_float32_net``: ask anew for each look-ahead."""
        forward = functools.partial(self._float32_net(), **self._look_ahead_options)
        if self.config.mirror_average:
            return functools.partial(mirror_averaged, forward)
        return forward

    def save_checkpoint(self, path: str | Path) -> None:
        """Write the state dict to ``path`` and the architecture to ``<path>.json``."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        torch.save(self.net.state_dict(), path)
        sidecar = {"model": self.plugin, "architecture": self.architecture()}
        sidecar_path(path).write_text(json.dumps(sidecar, indent=2), encoding="utf-8")
        log.info("saved %s weights to %s", self.plugin, path)


class GNNProcessModel(_LearnedProcessModel):
    """``filters.gnn``: the causal graph network; one set of weights for any link count."""

    plugin = "filters.gnn"
    n_links = None

    class Config(LearnedModelConfig):
        pass

    config: Config
    _look_ahead_options: ClassVar[dict[str, Any]] = {"with_force": False, "reuse_inputs": True}

    def _build(self) -> nn.Module:
        return GraphProcessNet(self.config.hidden)

    def architecture(self) -> dict[str, int]:
        return {"hidden": self.config.hidden}

    def predict_pose(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """:meth:`predict` without the finger force (zeros): ~10% faster."""
        prediction: Prediction = self.net(states, inputs, dt_s, with_force=False)
        return prediction


class FFProcessModel(_LearnedProcessModel):
    """``filters.ff``: the feed-forward baseline for a fixed number of links, or, with
    ``checkpoints``, one net per link count, picked by the fitted object's link count."""

    plugin = "filters.ff"

    class Config(LearnedModelConfig):
        n_links: int = Field(default=1, ge=1, le=FF_MAX_LINKS)
        checkpoints: dict[Annotated[int, Field(ge=1, le=FF_MAX_LINKS)], SkillPath] | None = Field(
            None, description="one checkpoint per link count, e.g. {1: checkpoints/ff1/"
            "ff_push.pt, 2: checkpoints/ff2/ff_push.pt}: the net of the fitted object's link "
            "count predicts, so the shape fit, not the skill, decides; replaces `checkpoint` "
            "and `n_links`",
        )

        @model_validator(mode="after")
        def _one_source(self) -> FFProcessModel.Config:
            if self.checkpoints is None:
                return self
            both = {"checkpoint", "n_links"} & self.model_fields_set
            if both:
                raise ValueError(
                    f"`checkpoints` gives the link counts and their weights; drop "
                    f"{' and '.join(f'`{key}`' for key in sorted(both))}"
                )
            if not self.checkpoints:
                raise ValueError("`checkpoints` is empty; give at least one link count")
            return self

    config: Config

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        counts = config.checkpoints
        self.n_links = config.n_links if counts is None else tuple(sorted(counts))
        super().__init__(config, ctx)
        if isinstance(self.net, FeedForwardByLinks):
            for n, path in sorted((counts or {}).items()):
                try:
                    load_checkpoint(self.net.net(n), Path(path), self.plugin, self._of(n))
                except DataError as error:
                    raise DataError(
                        f"`checkpoints` {n}: {error} (each key is the link count its "
                        "checkpoint was trained for)"
                    ) from None

    def _build(self) -> nn.Module:
        if isinstance(self.n_links, tuple):
            return FeedForwardByLinks(self.n_links, self.config.hidden)
        return FeedForwardProcessNet(self.config.n_links, self.config.hidden)

    def _of(self, n_links: int) -> dict[str, int]:
        return {"hidden": self.config.hidden, "n_links": n_links}

    def architecture(self) -> dict[str, int]:
        return self._of(self.config.n_links)

    def save_checkpoint(self, path: str | Path) -> None:
        if isinstance(self.n_links, tuple):
            raise ConfigError(
                "filters.ff with `checkpoints` holds one net per link count; train and save "
                "each with `n_links` (`vistac train` does so)"
            )
        super().save_checkpoint(path)


class AnalyticalProcessModel(Component):
    """``filters.analytical``: Lynch's quasi-static pushing of one homogeneous link, and of a
    chain of welded or hinged links by minimum power (:mod:`vistac.plugins.filters.chain`);
    a pull holds the grasped link's point between the fingers and lets the link turn there
    against ``grasp_friction_nm`` (None: rigidly). Fixed, hand-tuned process noise."""

    kind = "process_model"
    n_links = None

    class Config(ComponentConfig):
        pusher_friction: float = Field(default=0.5, ge=0.0)
        """mu_r between finger pad and object."""
        pusher_offset_m: float = Field(default=0.01, ge=0.0)
        """TCP to the leading pad face (the executor's ``pusher_offset_m``)."""
        contact_margin_m: float = Field(default=0.005, ge=0.0)
        pad_half_width_m: float = Field(default=0.012, ge=0.0)
        """Half width of the flat finger pad (line contact; 0: point contact)."""
        grasp_friction_nm: float | None = Field(default=0.1, ge=0.0)
        """Torque a pull's grasp holds before the link turns between the fingers; None: a
        rigid grasp. 0.1 N m predicted the simulated gripper's pulls best among 0.02-0.4 and
        rigid (docs/results.md)."""
        contact_normal: Literal["push", "box"] = "push"
        """The contact normal: the push direction, or the footprint box's side (see
        ``vistac.plugins.filters.analytical.pad_contact``)."""
        pressure: Pressure = "uniform"
        """How a link presses on the table: ``uniform`` over its footprint box, or
        ``linear``, centred under the CoM (a rigid link on an elastic table)."""
        position_std_m: float = Field(default=0.002, gt=0.0)
        theta_std_rad: float = Field(default=0.02, gt=0.0)
        speed_std_mps: float = Field(default=0.005, gt=0.0)
        rate_std_radps: float = Field(default=0.05, gt=0.0)

    config: Config

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.settings = PushSettings(
            pusher_friction=config.pusher_friction,
            pusher_offset_m=config.pusher_offset_m,
            contact_margin_m=config.contact_margin_m,
            pad_half_width_m=config.pad_half_width_m,
            contact_normal=config.contact_normal,
            pressure=config.pressure,
            grasp_friction_nm=config.grasp_friction_nm,
        )
        std = [config.position_std_m] * 2 + [config.theta_std_rad]
        std += [config.speed_std_mps] * 2 + [config.rate_std_radps]
        self.process_var = torch.tensor(std, dtype=DTYPE) ** 2

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        """states [..., C, 11 L - 1] -> Prediction with process_var [..., 6 L]."""
        n_links = layout_of(states).n_links
        turning_grasp = self.settings.grasp_friction_nm is not None
        if n_links == 1 and not (turning_grasp and bool((inputs.is_pull > 0.5).any())):
            return analytical_prediction(states, inputs, dt_s, self.settings, self.process_var)
        pose, force = chain_step(states, inputs, dt_s, self.settings)
        variance = self.process_var.repeat(n_links).expand(*inputs.tcp.shape[:-1], 6 * n_links)
        return Prediction(pose=pose, force_n=force, process_var=variance)
