"""Active iterative training of the process models (paper 1, IV-B2 and Fig. 10).

``vistac train SKILL.yaml --selection info_gain|uniform|random`` trains in rounds instead of on
one fixed data set:

0. Seed: the collection skill runs ``seed_interactions`` random interactions on every training
   object and ``val_interactions`` on every validation object (the validation set, fixed for
   all rounds and shared by all selections, so their errors compare). Each selector of
   ``extra_val`` adds a validation set of ``val_interactions`` interactions per validation
   object chosen by it (info gain with the collection skill's own model: the interactions
   the skill makes when deployed), scored every round next to the random one, which alone
   decides the threshold.
1. Each round trains every model of the preset on its replay buffer (all trajectories so far,
   the oldest dropped beyond ``buffer_size``, so the seed goes first) for ``epochs_per_round``
   epochs with early stopping, warm-started from the previous round, through the same losses
   as ``vistac train`` (rollouts, observation noise, end to end through the filter).
2. The validation error of the model is the mean squared open-loop rollout error of the pose
   (per component in units of 1 cm, 0.1 rad, 1 cm/s, 0.1 rad/s) plus that of the finger force
   (N): the MSE terms of the rollout loss, i.e. the paper's "pose and contact force prediction
   error" on the validation set.
3. At or below ``threshold`` the model is done; otherwise, up to ``max_rounds`` rounds, the
   collection skill runs ``per_round`` more interactions on every training object with its
   planner replaced by the selector. ``actions.info_gain`` looks ahead with the model just
   trained (and its observation-noise net) in the skill's dual filter, so the skill needs a
   ``filter`` component (skills/explore_active.yaml); each interaction is chosen after the
   belief update of the previous one, i.e. the k most informative actions in sequence rather
   than the paper's top k of one candidate set. Uniform and random data do not depend on the
   model, so all models share them. A run that records nothing (an action the arm may not
   carry out, say) leaves its object out of that collection, the seed and validation ones
   included, with a warning.

``trajectories_to_threshold`` is the size of everything collected of that interaction (seed
included) when the validation error first reached the threshold: the bars of Fig. 10; its
``_by_type`` form counts one object type's trajectories against that type's validation error.
Each selection, model and interaction keeps its own buffer, weights and rounds in
``active/<selection>/<model>_<interaction>/``; the final weights are copied into the output
folder under the names ``vistac train`` uses (the observation-noise net of the first model),
so ``vistac eval --checkpoints DIR`` reads them. Finished seed, validation, uniform and random
collection runs are reused when the data settings are unchanged, so the three selections run
into one folder one after the other train on the same seed and validation data, and
``active_training.png`` compares them.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from collections import Counter
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from vistac.errors import ConfigError, DataError, validation_issues
from vistac.plugins.filters.data import Trajectory, describe, load_trajectories, stack_equal_length
from vistac.plugins.filters.evaluate import (
    ff_checkpoint,
    model_override,
    offered_interactions,
    planner_override,
    read_skill,
)
from vistac.plugins.filters.train import (
    Interaction,
    ModelName,
    TrainConfig,
    batches,
    build_model,
    collect,
    object_files,
    preset_file,
    rollout_errors,
    train_interaction,
    window_steps,
)

log = logging.getLogger(__name__)

Selection = Literal["info_gain", "uniform", "random"]
_POSITION_SCALE_MM = 10.0
"""The pose loss scale of x and y (``train._POSE_SCALE``: 0.01 m) in mm."""
_ANGLE_SCALE_DEG = math.degrees(0.1)


class ActiveConfig(BaseModel):
    """Settings of active iterative training (a preset's ``active:`` block)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    selection: Selection = "info_gain"
    seed_interactions: int = Field(
        default=2, gt=0, description="random interactions per training object"
    )
    val_interactions: int = Field(default=3, gt=0, description="random interactions per val object")
    per_round: int = Field(
        default=2, gt=0, description="k, selected interactions per object per round"
    )
    max_rounds: int = Field(default=5, gt=0, description="training rounds, the seed round included")
    threshold: float = Field(
        default=0.5, ge=0, description="stop at this validation error or below"
    )
    epochs_per_round: int = Field(
        default=4, gt=0, description="epochs on the buffer per round (at most)"
    )
    buffer_size: int | None = Field(default=None, gt=0, description="cap on buffered trajectories")
    extra_val: tuple[Selection, ...] = Field(
        default=(),
        description="more validation sets, each scored every round next to the random one: "
        "val_interactions interactions per validation object chosen by this selector "
        "(info_gain with the collection skill's own model, i.e. the interactions the skill "
        "makes when deployed); the random set alone decides the threshold",
    )

    @field_validator("extra_val")
    @classmethod
    def _not_the_random_set(cls, selections: tuple[Selection, ...]) -> tuple[Selection, ...]:
        if "random" in selections or len(set(selections)) < len(selections):
            raise ValueError(
                "extra_val: the random validation set is always scored (it decides the "
                "threshold) and each selector is one set; give info_gain and/or uniform once"
            )
        return selections
    collect_overrides: tuple[str, ...] = ()
    """``--set`` overrides of the collection skill in every active-training run (the preset's
    own ``collect_overrides`` are for the plain collection skill and are not used)."""


_FAST = (
    "components.camera.with.width=160", "components.camera.with.height=120",
    "components.affordances.with.samples=16", "components.affordances.with.duration_s=3",
)  # fmt: skip
ACTIVE_PRESETS: dict[str, ActiveConfig] = {
    "tiny": ActiveConfig(seed_interactions=2, val_interactions=3, per_round=2, max_rounds=4,
                         epochs_per_round=4, collect_overrides=_FAST),
    "paper": ActiveConfig(seed_interactions=1, val_interactions=5, per_round=5, max_rounds=20,
                          epochs_per_round=10),
}  # fmt: skip
"""The active settings of ``--preset tiny|paper``; the ``tiny`` collection runs are shortened
(small camera images, 16 candidate actions, 3 s interactions: keys that collect_pushes.yaml and
explore_active.yaml share)."""


def active_settings(preset: str, **changes: Any) -> ActiveConfig:
    """The preset's active settings (a named preset or the ``active:`` block of a preset YAML
    file) with ``changes`` (None = keep) applied; invalid values are a ConfigError."""
    if preset in ACTIVE_PRESETS:
        base: dict[str, Any] = ACTIVE_PRESETS[preset].model_dump()
    else:
        base = dict(preset_file(Path(preset)).get("active") or {})
    base |= {key: value for key, value in changes.items() if value is not None}
    try:
        return ActiveConfig.model_validate(base)
    except ValidationError as error:
        raise ConfigError(validation_issues("active", error, ActiveConfig), preset) from None


# ---------------------------------------------------------------------------------------------
# Replay buffer and stop rule


class ReplayBuffer:
    """The trajectories to train on: everything added, the oldest dropped beyond ``capacity``."""

    def __init__(self, capacity: int | None = None) -> None:
        if capacity is not None and capacity < 1:
            raise ValueError(f"replay buffer capacity must be >= 1, got {capacity}")
        self.capacity = capacity
        self.trajectories: list[Trajectory] = []
        self.added = 0
        """All trajectories ever added (the x axis of Fig. 10)."""
        self.added_by_type: Counter[str] = Counter()
        """:attr:`added` per object type."""

    def add(self, trajectories: Iterable[Trajectory]) -> None:
        new = list(trajectories)
        self.added += len(new)
        self.added_by_type.update(t.spec.type for t in new)
        self.trajectories += new
        if self.capacity is not None:
            self.trajectories = self.trajectories[-self.capacity :]

    def __len__(self) -> int:
        return len(self.trajectories)


def stop_reason(
    val_error: float, threshold: float, rounds_done: int, max_rounds: int
) -> str | None:
    """Why training stops after ``rounds_done`` rounds: ``threshold`` once the validation error
    is at or below it, ``max_rounds`` after the last round, else None (another round)."""
    if val_error <= threshold:
        return "threshold"
    return "max_rounds" if rounds_done >= max_rounds else None


def trajectories_to_threshold(rounds: Sequence[dict[str, Any]], threshold: float) -> int | None:
    """Trajectories collected when the validation error first reached ``threshold`` (None:
    never)."""
    return next((r["trajectories"] for r in rounds if r["val_error"] <= threshold), None)


def trajectories_to_threshold_by_type(
    rounds: Sequence[dict[str, Any]], threshold: float
) -> dict[str, int | None]:
    """Per object type: the trajectories of that type collected when the validation error on
    that type's validation objects first reached ``threshold`` (None: never)."""
    types = sorted({kind for r in rounds for kind in r.get("by_type", {})})
    return {
        kind: trajectories_to_threshold(
            [r["by_type"][kind] for r in rounds if kind in r.get("by_type", {})], threshold
        )
        for kind in types
    }


# ---------------------------------------------------------------------------------------------
# Validation error


def validation_error(
    model: Any, windows: list[Trajectory], rollout_steps: int, batch_size: int
) -> dict[str, float]:
    """Open-loop prediction errors of ``model`` on the validation windows.

    ``val_error``: mean over rollout steps of the scaled pose MSE plus the force MSE (N^2), the
    stop criterion; also the position (mm), angle (deg) and force (N) RMSE.
    """
    pose_sq, force_sq, position_sq, angle_sq = [], [], [], []
    rng = np.random.default_rng(0)
    with torch.no_grad():
        for batch in batches(windows, batch_size, rng):
            for error, _, force_error in rollout_errors(model, batch, rollout_steps):
                per_link = error.reshape(*error.shape[:-1], -1, 6)  # [B, 1, L, 6]
                pose_sq.append(float(error.square().mean()))
                force_sq.append(float(force_error.square().mean()))
                position_sq.append(float(per_link[..., :2].square().mean()))
                angle_sq.append(float(per_link[..., 2].square().mean()))
    if not pose_sq:
        raise DataError("no validation windows to compute the validation error on")
    return {
        "val_error": float(np.mean(pose_sq) + np.mean(force_sq)),
        "position_rmse_mm": _POSITION_SCALE_MM * math.sqrt(np.mean(position_sq)),
        "angle_rmse_deg": _ANGLE_SCALE_DEG * math.sqrt(np.mean(angle_sq)),
        "force_rmse_n": math.sqrt(np.mean(force_sq)),
    }


def model_error(
    name: ModelName,
    kind: Interaction,
    work: Path,
    val: list[Trajectory],
    config: TrainConfig,
    steps: int | None = None,
) -> dict[str, float]:
    """:func:`validation_error` of the checkpoints in ``work`` on windows of ``steps`` steps
    (default :func:`window_steps` of ``val``): one GNN for every link count, one FF per link
    count (validation windows of a count without an FF are left out)."""
    windows = stack_equal_length(val, steps or window_steps(val))
    by_links: dict[int, list[Trajectory]] = {}
    for window in windows:
        by_links.setdefault(window.n_links, []).append(window)
    if name == "gnn":
        model = build_model(name, 1, config, work, work / f"gnn_{kind}.pt")
        return validation_error(model, windows, config.rollout_steps, config.batch_size)
    usable = []
    for n_links, group in sorted(by_links.items()):
        path = ff_checkpoint(work, kind, n_links)
        if path is None:
            log.warning("no FF for %d link(s): %d validation windows left out", n_links, len(group))
        else:
            usable.append((build_model(name, n_links, config, work, path), group))
    if not usable:
        raise DataError(f"no FF checkpoint in {work} fits the validation objects")
    parts = [validation_error(m, g, config.rollout_steps, config.batch_size) for m, g in usable]
    weights = [len(group) for _, group in usable]
    return {key: float(np.average([p[key] for p in parts], weights=weights)) for key in parts[0]}


# ---------------------------------------------------------------------------------------------
# Collection


def repeat_key(skill_data: dict[str, Any], skill: Path) -> str:
    """``tree.sequence.<i>.repeat``: the skill's top-level loop of interactions."""
    sequence = ((skill_data.get("tree") or {}).get("sequence")) or []
    for index, node in enumerate(sequence):
        if isinstance(node, dict) and "repeat" in node:
            return f"tree.sequence.{index}.repeat"
    raise ConfigError(
        f"{skill}: active training needs a skill whose tree is a sequence with a repeat of "
        "interactions (as collect_pushes.yaml and explore_active.yaml have)"
    )


class Collector:
    """Runs the collection skill: ``count`` interactions per object with a selector."""

    def __init__(self, skill: Path, config: TrainConfig, active: ActiveConfig) -> None:
        self.skill, self.config, self.active = skill, config, active
        self.skill_data = read_skill(skill)
        self.repeat = repeat_key(self.skill_data, skill)
        components = self.skill_data.get("components") or {}
        if "info_gain" in {active.selection, *active.extra_val} and "filter" not in components:
            raise ConfigError(
                f"{skill}: information gain (--selection info_gain or extra_val) predicts "
                "with the model in the skill's dual filter; use a collection skill with a "
                "filter component, e.g. skills/explore_active.yaml"
            )

    def run(
        self,
        objects: Sequence[Path],
        folder: Path,
        selection: Selection,
        count: int,
        seed: int,
        model: tuple[ModelName, Interaction, Path] | None = None,
    ) -> list[Trajectory]:
        """Collect under ``folder`` (finished runs are reused); ``model``: (name, interaction,
        checkpoint folder) of the model the skill's filter predicts with. An object whose run
        records nothing is left out, with a warning (``train_active`` stops when a whole
        collection has nothing of an interaction)."""
        trajectories: list[Trajectory] = []
        for path in objects:
            overrides = [*self.active.collect_overrides,
                         f"{self.repeat}.max={count}", f"{self.repeat}.until=null",
                         planner_override(selection, self.skill_data)]  # fmt: skip
            if model is not None:
                overrides += self._model_overrides(*model)
            config = self.config.model_copy(
                update={"collect_overrides": tuple(overrides), "seed": seed, "runs_per_object": 1}
            )
            try:
                trajectories += load_trajectories(collect(self.skill, [path], folder, config))
            except DataError as error:
                log.warning("left out %s from %s: %s", path.name, folder.name, error)
        return trajectories

    @staticmethod
    def _model_overrides(name: ModelName, kind: Interaction, work: Path) -> list[str]:
        override, why = model_override(name, work, kind)
        if override is None:
            raise DataError(f"active training: cannot select with {name}: {why}")
        noise = work / f"obs_noise_{kind}.pt"
        return [override, f"components.filter.with.noise_checkpoint={noise.resolve()}"]


# ---------------------------------------------------------------------------------------------
# Rounds


def train_rounds(
    name: ModelName,
    kind: Interaction,
    seed_data: list[Trajectory],
    val: list[Trajectory],
    collector: Collector,
    train_objects: list[Path],
    out_dir: Path,
    extra_val: dict[Selection, list[Trajectory]] | None = None,
) -> dict[str, Any]:
    """Active iterative training of one model on one interaction; its rounds and result.
    ``extra_val``: more validation sets by the selector that chose them (``extra_val`` of
    each round and ``trajectories_to_threshold_on`` of the result)."""
    config, active = collector.config, collector.active
    work = _work_dir(out_dir, active.selection, name, kind)
    shutil.rmtree(work, ignore_errors=True)  # round 0 starts from fresh weights
    torch.manual_seed(config.seed)
    buffer = ReplayBuffer(active.buffer_size)
    buffer.add(t for t in seed_data if t.kind == kind)
    rounds: list[dict[str, Any]] = []
    stopped = None
    while stopped is None:
        index = len(rounds)
        start_s = time.perf_counter()
        if index:
            buffer.add(_collect_round(name, kind, index, collector, train_objects, work))
        collect_s = time.perf_counter() - start_s
        errors = train_round(name, kind, index, buffer.trajectories, val, collector, work)
        errors["extra_val"] = {
            selection: model_error(name, kind, work, trajectories, collector.config)
            for selection, trajectories in (extra_val or {}).items()
        }
        by_type = errors.pop("by_type")
        for object_type, type_errors in by_type.items():
            type_errors["trajectories"] = buffer.added_by_type[object_type]
        rounds.append({
            "round": index, "trajectories": buffer.added, "buffer": len(buffer), **errors,
            "by_type": by_type, "collect_time_s": collect_s,
            "time_s": time.perf_counter() - start_s,
        })  # fmt: skip
        log.info("%s %s round %d: %d trajectories, validation error %.4g",
                 name, kind, index, buffer.added, errors["val_error"])  # fmt: skip
        stopped = stop_reason(errors["val_error"], active.threshold, len(rounds), active.max_rounds)
    return {
        "rounds": rounds, "stopped": stopped, "threshold": active.threshold,
        "trajectories_to_threshold": trajectories_to_threshold(rounds, active.threshold),
        "trajectories_to_threshold_by_type": trajectories_to_threshold_by_type(
            rounds, active.threshold
        ),
        "trajectories_to_threshold_on": {
            selection: trajectories_to_threshold(
                [r["extra_val"][selection] | {"trajectories": r["trajectories"]} for r in rounds],
                active.threshold,
            )
            for selection in extra_val or {}
        },
        "checkpoints": str(work),
    }  # fmt: skip


def train_round(
    name: ModelName,
    kind: Interaction,
    index: int,
    buffer: list[Trajectory],
    val: list[Trajectory],
    collector: Collector,
    work: Path,
) -> dict[str, Any]:
    """Train on the buffer (from the checkpoints in ``work`` after round 0) and score the
    model: :func:`model_error` on all validation objects, ``by_type`` the same per object type
    (types the model cannot predict, an FF without that link count, left out), and the epochs
    run."""
    config = collector.config
    epochs = collector.active.epochs_per_round
    round_config = config.model_copy(
        update={"models": (name,), "seed": config.seed + index, "epochs": epochs}
    )
    data = {"train": buffer, "val": val}
    trained = train_interaction(kind, data, round_config, work, warm_start=index > 0)
    steps = window_steps(val)
    by_type: dict[str, dict[str, float]] = {}
    for object_type in sorted({t.spec.type for t in val}):
        subset = [t for t in val if t.spec.type == object_type]
        try:
            by_type[object_type] = model_error(name, kind, work, subset, config, steps)
        except DataError as error:
            log.warning("no %s validation error on %s objects: %s", name, object_type, error)
    errors = model_error(name, kind, work, val, config, steps)
    return errors | {"by_type": by_type, "epochs": _epochs(trained[name])}


def _epochs(report: dict[str, Any]) -> int:
    """Process-model epochs a round ran (summed over the FF's per-link-count models)."""
    if "history" in report:
        return len(report["history"])
    return sum(_epochs(part) for part in report.values() if isinstance(part, dict))


def _collect_round(
    name: ModelName,
    kind: Interaction,
    index: int,
    collector: Collector,
    objects: list[Path],
    work: Path,
) -> list[Trajectory]:
    """The ``per_round`` selected interactions per object of round ``index`` (of ``kind``);
    info gain predicts with the checkpoints in ``work``."""
    selection = collector.active.selection
    model: tuple[ModelName, Interaction, Path] | None = None
    if selection == "info_gain":
        folder = work / "data" / f"round_{index:02d}"
        model = (name, kind, work)
    else:  # the data do not depend on the model: shared by all models
        folder = work.parents[1] / "data" / selection / f"round_{index:02d}"
    seed = collector.config.seed + 1 + index
    count = collector.active.per_round
    new = collector.run(objects, folder, selection, count, seed, model)
    return [t for t in new if t.kind == kind]


def _data_stamp(skill: Path, config: TrainConfig, active: ActiveConfig) -> dict[str, Any]:
    """What the shared collections (seed, validation, uniform, random) depend on."""
    keys = ("seed_interactions", "val_interactions", "per_round", "collect_overrides")
    return {
        "skill": str(skill.resolve()), "objects": config.objects, "seed": config.seed,
        "shipped_train": config.shipped_train, "shipped_val": config.shipped_val,
        "max_objects": config.max_objects,
        **{key: getattr(active, key) for key in keys},
    }  # fmt: skip


def _work_dir(out_dir: Path, selection: Selection, name: ModelName, kind: Interaction) -> Path:
    """Where one selection keeps a model's rounds, checkpoints and (info gain) data."""
    return out_dir / "active" / selection / f"{name}_{kind}"


def _prepare(out_dir: Path, stamp: dict[str, Any]) -> None:
    """Drop the collections and results of earlier runs with other data settings."""
    data = out_dir / "active" / "data"
    path = data / "settings.json"
    stamp_json = json.loads(json.dumps(stamp))
    if path.is_file() and json.loads(path.read_text(encoding="utf-8")) != stamp_json:
        log.info("data settings changed: collecting again in %s", data)
        shutil.rmtree(out_dir / "active")
    data.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(stamp_json, indent=2), encoding="utf-8")


def training_kinds(
    skill_data: dict[str, Any], config: TrainConfig, skill: Path
) -> list[Interaction]:
    """The preset's interactions that the skill's action sampler proposes."""
    offered = offered_interactions(skill_data)
    kinds = [kind for kind in config.interactions if kind in offered]
    if not kinds:
        raise ConfigError(
            f"{skill}: its action sampler proposes {sorted(offered) or 'no interactions'}, "
            f"the preset trains {list(config.interactions)}: nothing to train"
        )
    skipped = [kind for kind in config.interactions if kind not in kinds]
    if skipped:
        log.info("%s proposes no %s: training %s only", skill, "/".join(skipped), "/".join(kinds))
    return kinds


def train_active(
    skill: Path, out_dir: Path, config: TrainConfig, active: ActiveConfig
) -> dict[str, Any]:
    """Active iterative training of every model and interaction of the preset; writes the
    final checkpoints and ``train.json`` to ``out_dir`` (the report also to
    ``active/<selection>/train.json``) and ``active_training.png``, which compares every
    selection trained in ``out_dir`` on the same data settings."""
    start_s = time.perf_counter()
    collector = Collector(skill, config, active)
    kinds = training_kinds(collector.skill_data, config, skill)
    out_dir.mkdir(parents=True, exist_ok=True)
    _prepare(out_dir, _data_stamp(skill, config, active))
    files = object_files(config, skill.parent, out_dir)
    data = out_dir / "active" / "data"
    seed_data = collector.run(files["train"], data / "seed", "random",
                              active.seed_interactions, config.seed)  # fmt: skip
    val = collector.run(files["val"], data / "val", "random", active.val_interactions,
                        config.seed + 1)  # fmt: skip
    extra = {selection: collector.run(files["val"], data / f"val_{selection}", selection,
                                      active.val_interactions, config.seed + 1)
             for selection in active.extra_val}  # fmt: skip
    report: dict[str, Any] = {
        "mode": "active", "selection": active.selection,
        "active": active.model_dump(mode="json"), "preset": config.model_dump(mode="json"),
        "data": {"seed": describe(seed_data), "val": describe(val)}
        | {f"val_{selection}": describe(extra[selection]) for selection in extra},
    }  # fmt: skip
    for kind in kinds:
        val_kind = [t for t in val if t.kind == kind]
        if not val_kind or not any(t.kind == kind for t in seed_data):
            raise DataError(f"no {kind} trajectories in the seed or validation collection")
        extra_kind = {sel: [t for t in extra[sel] if t.kind == kind] for sel in extra}
        if not all(extra_kind.values()):
            raise DataError(f"no {kind} trajectories in an extra_val collection: "
                            f"{', '.join(sel for sel, ts in extra_kind.items() if not ts)}")
        report[kind] = {
            name: train_rounds(name, kind, seed_data, val_kind, collector, files["train"],
                               out_dir, extra_kind)
            for name in config.models
        }  # fmt: skip
    _publish(out_dir, active.selection, kinds, config.models)
    report["time_s"] = time.perf_counter() - start_s
    text = json.dumps(report, indent=2)
    (out_dir / "train.json").write_text(text, encoding="utf-8")
    (out_dir / "active" / active.selection / "train.json").write_text(text, encoding="utf-8")
    plot_rounds(selection_reports(out_dir), out_dir / "active_training.png")
    return report


def selection_reports(out_dir: Path) -> list[dict[str, Any]]:
    """The reports of every selection trained in ``out_dir`` (the latest run of each)."""
    paths = sorted((out_dir / "active").glob("*/train.json"))
    return [json.loads(path.read_text(encoding="utf-8")) for path in paths]


def _publish(
    out_dir: Path,
    selection: Selection,
    kinds: Sequence[Interaction],
    models: Sequence[ModelName],
) -> None:
    """Copy each model's final weights to ``out_dir`` (and the first model's noise net)."""
    for position, name in enumerate(models):
        for kind in kinds:
            work = _work_dir(out_dir, selection, name, kind)
            patterns = [f"{name}_{kind}.pt*", f"ff*/{name}_{kind}.pt*"]
            patterns += [f"obs_noise_{kind}.pt*"] if position == 0 else []
            for pattern in patterns:
                for source in work.glob(pattern):
                    target = out_dir / source.relative_to(work)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(source, target)


# ---------------------------------------------------------------------------------------------
# Reports


def summary_lines(report: dict[str, Any]) -> list[str]:
    """One line per model and interaction: the trajectories it needed, or how far it got."""
    lines = []
    for kind in ("push", "pull"):
        for name, result in (report.get(kind) or {}).items():
            last = result["rounds"][-1]
            label = f"{name} {kind} ({report['selection']})"
            needed = result["trajectories_to_threshold"]
            if needed is not None:
                lines.append(f"{label}: validation error {last['val_error']:.4g} <= "
                             f"{result['threshold']:g} after {needed} trajectories "
                             f"(round {last['round']})")  # fmt: skip
            else:
                lines.append(f"{label}: validation error {last['val_error']:.4g} > "
                             f"{result['threshold']:g} after {len(result['rounds'])} rounds, "
                             f"{last['trajectories']} trajectories (not reached)")  # fmt: skip
            lines += _type_lines(result)
            lines += _extra_lines(result)
    return lines


def _extra_lines(result: dict[str, Any]) -> list[str]:
    """Per extra validation set: the trajectories it needed there, or its last error."""
    lines = []
    for selection, needed in result.get("trajectories_to_threshold_on", {}).items():
        error = result["rounds"][-1]["extra_val"][selection]["val_error"]
        reached = f"reached after {needed}" if needed is not None else "not reached"
        lines.append(f"  on {selection} validation interactions: validation error {error:.4g} "
                     f"(threshold {reached})")  # fmt: skip
    return lines


def _type_lines(result: dict[str, Any]) -> list[str]:
    """Per object type: the trajectories of that type it needed, or its last error."""
    lines = []
    last = result["rounds"][-1].get("by_type", {})
    for object_type, needed in result.get("trajectories_to_threshold_by_type", {}).items():
        if needed is not None:
            lines.append(f"  {object_type}: threshold reached after {needed} trajectories")
        elif object_type in last:
            errors = last[object_type]
            lines.append(f"  {object_type}: validation error {errors['val_error']:.4g} after "
                         f"{errors['trajectories']} trajectories (not reached)")  # fmt: skip
    return lines


def plot_rounds(reports: Sequence[dict[str, Any]], path: Path) -> None:
    """Validation error vs trajectories collected (Fig. 10): one panel for all validation
    objects and one per object type, one line per selection, model and interaction."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = _curves(reports)
    panels = sorted({panel for panel, _ in curves}, key=lambda p: (p != "all", p))
    figure, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.5), squeeze=False)
    for axis, panel in zip(axes[0], panels, strict=True):
        for (where, label), points in curves.items():
            if where == panel:
                axis.plot(*zip(*points, strict=True), marker="o", label=label)
        thresholds = {report["active"]["threshold"] for report in reports}
        for threshold in thresholds:
            axis.axhline(threshold, color="k", linestyle="--", linewidth=1)
        of_type = "" if panel.startswith("all") else f" ({panel})"
        axis.set_xlabel("trajectories collected" + of_type)
        axis.set_ylabel("validation error")
        axis.set_title(f"validation objects: {panel}")
        axis.grid(alpha=0.3)
        axis.legend(fontsize="small")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def _curves(reports: Sequence[dict[str, Any]]) -> dict[tuple[str, str], list[tuple[int, float]]]:
    """(panel, label) -> [(trajectories, validation error)] per round; panel ``all``, an
    object type, whose x is that type's trajectories, or ``all, <selector> interactions`` (an
    extra validation set)."""
    curves: dict[tuple[str, str], list[tuple[int, float]]] = {}
    for report in reports:
        for kind in ("push", "pull"):
            for name, result in (report.get(kind) or {}).items():
                label = f"{report['selection']} {name} {kind}"
                for r in result["rounds"]:
                    curves.setdefault(("all", label), []).append(
                        (r["trajectories"], r["val_error"])
                    )
                    for selection, errors in r.get("extra_val", {}).items():
                        curves.setdefault((f"all, {selection} interactions", label), []).append(
                            (r["trajectories"], errors["val_error"])
                        )
                    for object_type, errors in r.get("by_type", {}).items():
                        curves.setdefault((object_type, label), []).append(
                            (errors["trajectories"], errors["val_error"])
                        )
    return curves
