"""``vistac eval``: compare process models and action selectors on objects (paper 1, IV-B3, IV-D).

For every object and variant the exploration skill runs once with the same seed, so the look
agrees. A variant is a process model with an action selector (paper 1, IV-D, Tables II-III):
A-GNN, A-FF and A-Analytical choose each action by N-step information gain
(``actions.info_gain``, 2.5 s look-ahead), U-GNN by ``actions.uniform`` (evenly spaced push
directions) and R-GNN by ``actions.random``. GNN-fixed runs the GNN with
``estimate_parameters: false`` and the random selector for the pose-tracking comparison
(Fig. 15): with the same seed it executes R-GNN's actions, so the two differ only in whether
the parameters are estimated.

Parameter error. NRMSE per parameter = RMSE over the runs of (estimate - truth) divided by the
parameter's range over the object set. Mass, table friction and joint friction use the ranges
the 120 configurations are drawn from (:data:`vistac.objects.MASS_RANGE_KG`, ...). The CoM
error is the distance between the estimated and the true CoM: the estimate lives in the
fitted superquadric's frame, whose origin and yaw differ from the true link frame's (a
superquadric of a symmetric footprint may be turned by pi, its centre is not the footprint's
centroid), so the true CoM is expressed in the fitted frame as it lay at the first filter step
of the run (before the first push moves the object). It is normalised by the range of the
radial CoM over the 120 generated configurations. Belief links are matched to true links by
their positions at that step (nearest, over all assignments).

Whole object. Of a welded pair, a push shows the total mass and the combined CoM, not how they
split between the links; the whole-object table scores those two (RMSE in kg and mm, the CoM
in the world frame at the first filter step) for every multi-link object, next to the prior.

Pose tracking. The belief's poses are those of the fitted superquadric frames, the truth the
link frames, so each step is compared as a change from the episode's first step: the error is
the distance between the belief's position and the true position of the body point that sat
at the belief's position at the first step (the link's displacement plus the rotation of that
offset), and the difference of the two rotations since the first step.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import shutil
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
from pydantic import ValidationError
from vistac.errors import ConfigError, DataError, VistacError
from vistac.objects import (
    FRICTION_RANGE,
    JOINT_FRICTION_RANGE_NM,
    MASS_RANGE_KG,
    OBJECT_TYPES,
    ObjectSpec,
    com_in_frames,
    generate_configurations,
    interleave_types,
    load_object,
    match_links,
    to_world_xy,
    write_configurations,
)
from vistac.plugins.filters.component import Prior
from vistac.plugins.filters.identifiable import welded_pair_posterior
from vistac.plugins.filters.models import FF_MAX_LINKS, LearnedModelConfig
from vistac.recording import refuse_file_as_folder
from vistac.skill import apply_overrides, read_yaml
from vistac.types import GaussianBelief

log = logging.getLogger(__name__)

MODELS: tuple[str, ...] = ("gnn", "ff", "analytical", "physics")
INFO_GAIN_HORIZON_S = 2.5
"""Look-ahead of ``actions.info_gain`` (paper 1, IV-B2; skills/explore_active.yaml)."""


@dataclass(frozen=True)
class Variant:
    """A process model run with an action selector: one column of the tables."""

    key: str
    """``--variants`` name and run folder, e.g. ``a-gnn``."""
    label: str
    """Table column and ``variant`` of the eval.json records, e.g. ``A-GNN``."""
    model: str
    selector: str
    estimate_parameters: bool = True


VARIANTS: tuple[Variant, ...] = (
    Variant("a-gnn", "A-GNN", "gnn", "info_gain"),
    Variant("u-gnn", "U-GNN", "gnn", "uniform"),
    Variant("r-gnn", "R-GNN", "gnn", "random"),
    Variant("a-ff", "A-FF", "ff", "info_gain"),
    Variant("a-analytical", "A-Analytical", "analytical", "info_gain"),
    Variant("gnn-fixed", "GNN-fixed", "gnn", "random", estimate_parameters=False),
    Variant("a-physics", "A-Physics", "physics", "info_gain"),
)
"""Every variant ``vistac eval`` knows, in table order. ``a-physics`` (``sim.physics``: the
simulator as the process model) only replays another variant's runs (``--paired``): a
look-ahead that simulates every sigma point would take hours a run."""
UNTRAINED_MODELS: dict[str, str] = {"analytical": "filters.analytical", "physics": "sim.physics"}
"""The models without checkpoints, by name, and their plugins."""
REPLAY_ONLY_MODELS: tuple[str, ...] = ("physics",)
"""Models ``vistac eval`` runs only as replays of another variant's interactions."""
FAMILIES: tuple[str, ...] = ("m", "f", "CoM", "f_j")
"""Parameter families of the tables: mass, table friction, CoM, joint friction."""
SPLITS: tuple[str, ...] = ("train", "val", "test")
OBJECT_SET_SEED = 0
"""Seed of the generated object set (``vistac objects generate`` default)."""

Value = float | tuple[float, float]
"""A scalar parameter, or a CoM (x, y) in the fitted frame (m)."""
Pairs = dict[str, tuple[Value, Value]]
"""Row name (``m_0``, ``CoM_1``, ``f_j_0``) -> (estimate, truth)."""


# ---------------------------------------------------------------------------------------------
# Normalisation ranges


def radial_com(com_x: float, com_y: float) -> float:
    """Distance (m) of the CoM from the link frame's origin; invariant to the frame's yaw."""
    return math.hypot(com_x, com_y)


def _span(values: Iterable[float]) -> float:
    array = np.fromiter(values, dtype=np.float64)
    return float(array.max() - array.min())


def parameter_ranges(
    specs: Sequence[ObjectSpec] | None = None, empirical: bool = False
) -> dict[str, float]:
    """The normalisation range of each family: {"m": kg, "f": -, "CoM": m, "f_j": N m}.

    ``specs``: the object set (default: the 120 generated configurations). ``empirical``:
    False takes m, f and f_j from the ranges the set is drawn from and only the radial CoM
    from the set; True takes all four from the set's values.
    """
    specs = list(specs) if specs is not None else generate_configurations(OBJECT_SET_SEED)
    links = [link for spec in specs for link in spec.links]
    ranges = {"CoM": _span(radial_com(*link.com_m) for link in links)}
    if empirical:
        joints = [spec.joint.friction_nm for spec in specs if spec.joint is not None]
        ranges |= {
            "m": _span(link.mass_kg for link in links),
            "f": _span(link.friction for link in links),
            "f_j": _span(joints) if joints else float("nan"),
        }
    else:
        ranges |= {
            "m": MASS_RANGE_KG[1] - MASS_RANGE_KG[0],
            "f": FRICTION_RANGE[1] - FRICTION_RANGE[0],
            "f_j": JOINT_FRICTION_RANGE_NM[1] - JOINT_FRICTION_RANGE_NM[0],
        }
    return {family: ranges[family] for family in FAMILIES}


# ---------------------------------------------------------------------------------------------
# Parameter errors


def family_of(row: str) -> str:
    """``m_0`` -> ``m``, ``CoM_1`` -> ``CoM``, ``f_j_0`` -> ``f_j``."""
    return row.rsplit("_", 1)[0]


def parameter_pairs(
    belief: dict[str, dict[str, float]], truth: dict[str, float], links: dict[int, int]
) -> Pairs:
    """(estimate, truth) per table row of one belief; ``links`` maps belief to true links.

    Rows are named by the true link: ``m_l``, ``f_l``, ``CoM_l`` ((x, y) m, in the frame the
    belief's are: see :func:`truth_in_belief_frames`), ``f_j_k``.
    """
    pairs: Pairs = {}
    for b, t in links.items():
        if f"m_{b}" not in belief or f"m_{t}" not in truth:
            continue
        mean = {key: belief[f"{key}_{b}"]["mean"] for key in ("m", "f", "com_x", "com_y")}
        pairs[f"m_{t}"] = (mean["m"], truth[f"m_{t}"])
        pairs[f"f_{t}"] = (mean["f"], truth[f"f_{t}"])
        if f"com_x_{t}" in truth:
            pairs[f"CoM_{t}"] = (
                (mean["com_x"], mean["com_y"]),
                (truth[f"com_x_{t}"], truth[f"com_y_{t}"]),
            )
    for name, value in truth.items():
        if name.startswith("f_j_") and name in belief:
            pairs[name] = (belief[name]["mean"], value)
    return pairs


def normalised_errors(
    belief: dict[str, dict[str, float]], truth: dict[str, float], links: dict[int, int]
) -> list[tuple[str, float, float]]:
    """(belief entry, ``(estimate - truth) / std``, std) of m, f, com_x and com_y per matched
    link (``links``: belief to true link) and of every joint friction: an honest belief has
    about 95 % of the normalised errors within +-2."""
    names = [(f"{key}_{b}", f"{key}_{t}") for b, t in links.items()
             for key in ("m", "f", "com_x", "com_y")]  # fmt: skip
    names += [(name, name) for name in truth if name.startswith("f_j_")]
    return [
        (ours, (belief[ours]["mean"] - truth[theirs]) / belief[ours]["std"], belief[ours]["std"])
        for ours, theirs in names
        if ours in belief and theirs in truth and belief[ours]["std"] > 0
    ]


def log_score(entry: str, z: float, std: float, ranges: dict[str, float]) -> float:
    """Gaussian negative log likelihood of the truth under a belief entry's marginal, the
    std in units of the entry family's range (``com_x_0`` -> CoM): rewards an estimate that
    is close and a std that is honest; a belief that is sure and wrong scores worst."""
    family = "CoM" if entry.startswith("com_") else family_of(entry)
    return 0.5 * z**2 + math.log(std / ranges[family]) + 0.5 * math.log(2 * math.pi)


def nrmse(pairs: Sequence[tuple[Value, Value]], value_range: float) -> float:
    """RMSE of the error ``|estimate - truth|`` (a distance for a CoM's (x, y)) over
    ``pairs`` divided by ``value_range``; NaN if empty."""
    if not pairs or not value_range > 0:
        return float("nan")
    errors = [np.linalg.norm(np.subtract(estimate, truth)) for estimate, truth in pairs]
    return float(np.sqrt(np.mean(np.square(errors))) / value_range)


def nrmse_rows(runs: Sequence[Pairs], ranges: dict[str, float]) -> dict[str, float]:
    """NRMSE of every row over the runs, plus ``overall`` = mean of the finite rows."""
    names = sorted({name for pairs in runs for name in pairs}, key=_row_order)
    rows = {
        name: nrmse([pairs[name] for pairs in runs if name in pairs], ranges[family_of(name)])
        for name in names
    }
    finite = [value for value in rows.values() if math.isfinite(value)]
    rows["overall"] = float(np.mean(finite)) if finite else float("nan")
    return rows


def _row_order(name: str) -> tuple[int, int]:
    family, link = name.rsplit("_", 1)
    return (FAMILIES.index(family), int(link))


def product_posterior_mean(product: float) -> tuple[float, float]:
    """``E[m | m f = product]`` and ``E[f | m f = product]`` for m and f independent and
    uniform over the object set's ranges (:data:`vistac.objects.MASS_RANGE_KG`,
    :data:`vistac.objects.FRICTION_RANGE`): along ``f = product / m`` the density of m is
    ``1 / m`` on the masses that keep f in its range."""
    (m_lo, m_hi), (f_lo, f_hi) = MASS_RANGE_KG, FRICTION_RANGE
    low, high = max(m_lo, product / f_hi), min(m_hi, product / f_lo)
    if high <= low * (1 + 1e-9):
        return low, product / low
    log_ratio = math.log(high / low)
    return (high - low) / log_ratio, product * (1 / low - 1 / high) / log_ratio


def prior_pairs(truth: Pairs, prior: Prior) -> Pairs:
    """``truth`` (the pairs of a scored run) with the prior's means as the estimates."""
    means: dict[str, Value] = {"m": prior.mass_kg[0], "f": prior.friction[0],
                               "CoM": (prior.com_m[0], prior.com_m[0]),
                               "f_j": prior.joint_friction_nm[0]}  # fmt: skip
    return {row: (means[family_of(row)], value) for row, (_, value) in truth.items()}


def product_known_pairs(truth: Pairs) -> Pairs:
    """``truth`` with every CoM and joint friction exact and each link's m and f the best
    estimate from their product alone (:func:`product_posterior_mean`)."""
    pairs = {row: (value, value) for row, (_, value) in truth.items()}
    for row in truth:
        if family_of(row) == "m" and f"f_{row[2:]}" in truth:
            mass, friction = cast(float, truth[row][1]), cast(float, truth[f"f_{row[2:]}"][1])
            m_hat, f_hat = product_posterior_mean(mass * friction)
            pairs[row], pairs[f"f_{row[2:]}"] = (m_hat, mass), (f_hat, friction)
    return pairs


HELD_BEND_RAD = math.radians(3.0)
"""A hinge that never turned farther than this from its first angle in a run *held*: the pair
moved as one rigid body (a hinge that slips turns 5 to 45 deg a push)."""


def hinges_held(record: dict[str, Any]) -> bool:
    """Whether ``record`` (a scored run) is of a hinged pair whose hinge held
    (:data:`HELD_BEND_RAD`; ``joint_bends_rad`` from :func:`largest_bends_rad`)."""
    bends = record.get("joint_bends_rad") or []
    return record["type"] == "articulated" and len(bends) == 1 and bends[0] < HELD_BEND_RAD


def load_known_pairs(record: dict[str, Any], prior: Prior | None = None) -> Pairs | None:
    """``record``'s pairs (a scored run, rows named by the true link) estimated from what
    quasi-static pushes show of each rigid body, its friction load and load centre, exactly:
    of a single link or a hinged pair whose hinge turned :func:`product_known_pairs`; of a
    welded pair (heterogeneous), or a hinged one whose hinges held (:func:`hinges_held`),
    the posterior means of :func:`~vistac.plugins.filters.identifiable.welded_pair_posterior`,
    each CoM's error (a distance when scored) put on the truth in the link frame's axes, and
    a held joint's friction at ``prior``'s mean (holding shows only a lower bound). None when
    the record names no object file to read the pair from."""
    truth = record["parameters"]
    held = hinges_held(record)
    if record["type"] != "heterogeneous" and not held:
        return product_known_pairs(truth)
    path = record.get("object_file")
    if not path or not Path(path).is_file():
        return None
    spec = load_object(path)
    pairs = product_known_pairs(truth)
    for link, (mass, friction, com) in enumerate(welded_pair_posterior(spec)):
        for row, estimate in ((f"m_{link}", mass), (f"f_{link}", friction)):
            if row in truth:
                pairs[row] = (estimate, truth[row][1])
        if f"CoM_{link}" in truth:
            true_com = truth[f"CoM_{link}"][1]
            error = com - np.asarray(spec.links[link].com_m)
            moved = (float(true_com[0] + error[0]), float(true_com[1] + error[1]))
            pairs[f"CoM_{link}"] = (moved, true_com)
    if held:
        joint_friction = (prior or Prior()).joint_friction_nm[0]
        pairs |= {row: (joint_friction, value) for row, (_, value) in truth.items()
                  if family_of(row) == "f_j"}  # fmt: skip
    return pairs


REFERENCES: tuple[str, ...] = ("Prior", "m·f known", "load known")
"""Reference columns of the NRMSE tables, scored on the objects the variants ran on."""


def reference_records(records: Sequence[dict[str, Any]], prior: Prior) -> list[dict[str, Any]]:
    """One record per object and interaction for each of :data:`REFERENCES`: the prior's
    means (the run's own first belief where its summary has one, e.g. a CoM prior from the
    fitted shape; else ``prior``'s), and an estimator that knows each link's CoM, the joint
    friction and the product m f exactly (what the force of a quasi-static push shows) but
    not m and f apart."""
    truths: dict[tuple[str, str], dict[str, Any]] = {}
    for record in records:
        if record["status"] == "ok" and record["estimate_parameters"]:
            truths.setdefault((record["object"], record["kind"]), record)
    references = []
    for record in truths.values():
        base = {key: record[key] for key in ("object", "type", "kind")}
        prior_means = record.get("prior") or prior_pairs(record["parameters"], prior)
        whole = record.get("whole_object")
        estimates = (prior_means, product_known_pairs(record["parameters"]),
                     load_known_pairs(record, prior))  # fmt: skip
        for label, pairs in zip(REFERENCES, estimates, strict=True):
            if pairs is None:
                continue
            reference = base | {"variant": label, "status": "ok", "parameters": pairs}
            if label == "Prior" and whole and whole["prior"]:
                reference["whole_object"] = whole | {"estimate": whole["prior"]}
            references.append(reference)
    return references


# ---------------------------------------------------------------------------------------------
# Pose tracking


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped to [-pi, pi)."""
    return np.asarray((angle + np.pi) % (2 * np.pi) - np.pi)


def pose_change_errors(belief: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Errors of the pose changes since the first step, for frames fixed to the same bodies.

    belief, truth: [T, L, 3] = (x_m, y_m, theta_rad) per step and (matched) link, the belief in
    the fitted frames, the truth in the link frames. Returns (position error [T, L] in m, the
    distance from the belief's position to the true track of the body point at the belief's
    first position; angle error [T, L] in rad, |change of belief theta - change of true theta|).
    """
    turn = wrap_angle(truth[..., 2] - truth[:1, :, 2])  # [T, L]
    offset = belief[:1, :, :2] - truth[:1, :, :2]  # [1, L, 2] world, at the first step
    c, s = np.cos(turn), np.sin(turn)
    rotated = np.stack(
        [c * offset[..., 0] - s * offset[..., 1], s * offset[..., 0] + c * offset[..., 1]], -1
    )
    point = truth[..., :2] + rotated  # [T, L, 2] true track of that body point
    position = np.linalg.norm(belief[..., :2] - point, axis=-1)
    belief_turn = wrap_angle(belief[..., 2] - belief[:1, :, 2])
    return position, np.abs(wrap_angle(belief_turn - turn))


def belief_poses(steps: Sequence[dict[str, Any]], links: Sequence[int]) -> np.ndarray:
    """The filter's link poses [T, len(links), 3] from ``filter_steps`` entries."""
    poses = [GaussianBelief.link_poses(step, links) for step in steps]
    return np.array(poses, dtype=np.float64).reshape(len(steps), len(links), 3)


def episode_true_poses(run_dir: Path, episode: int) -> np.ndarray:
    """The true link poses [T, L, 3] (x m, y m, theta rad) of one episode of a run."""
    path = run_dir / "episodes" / f"{episode:04d}" / "data.npz"
    try:
        with np.load(path) as data:
            return np.asarray(data["object_pose"], dtype=np.float64)
    except (OSError, KeyError) as error:
        raise DataError(
            f"{path}: no object_pose ({error}); delete {run_dir} to run it again"
        ) from None


def largest_bends_rad(run_dir: Path) -> list[float]:
    """How far each true joint k (links k, k + 1) turned from its angle at the run's first
    recorded step, the largest over every step of every episode: [L - 1] (rad)."""
    episodes = sorted((run_dir / "episodes").glob("*/data.npz"))
    if not episodes:
        return []
    poses = [episode_true_poses(run_dir, int(path.parent.name)) for path in episodes]
    bends = np.concatenate([pose[:, 1:, 2] - pose[:, :-1, 2] for pose in poses])  # [T, L - 1]
    return [float(b) for b in np.abs(wrap_angle(bends - bends[0])).max(axis=0, initial=0.0)]


def tracking_errors(
    run_dir: Path, summary: dict[str, Any], links: dict[int, int]
) -> dict[str, float]:
    """Mean position (m) and angle (rad) error of a run's per-step link poses, all episodes.

    Steps are matched in order within each episode (``filter_steps`` against the episode's
    ``data.npz`` ``object_pose``).
    """
    positions: list[np.ndarray] = []
    angles: list[np.ndarray] = []
    for index, steps in _steps_by_episode(summary.get("filter_steps", [])).items():
        truth = episode_true_poses(run_dir, index)
        count = min(len(steps), len(truth))
        if count < 1 or not links:
            continue
        belief = belief_poses(steps[:count], list(links))
        position, angle = pose_change_errors(belief, truth[:count, list(links.values())])
        positions.append(position.ravel())
        angles.append(angle.ravel())
    if not positions:
        return {"position_m": float("nan"), "angle_rad": float("nan"), "steps": 0}
    return {
        "position_m": float(np.concatenate(positions).mean()),
        "angle_rad": float(np.concatenate(angles).mean()),
        "steps": int(sum(len(p) for p in positions) // max(len(links), 1)),
    }


def _steps_by_episode(steps: Sequence[dict[str, Any]]) -> dict[int, list[dict[str, Any]]]:
    grouped: dict[int, list[dict[str, Any]]] = {}
    for step in steps:
        grouped.setdefault(int(step["episode"]), []).append(step)
    return grouped


FirstPoses = tuple[np.ndarray, np.ndarray] | None
"""Belief [Lb, 3] and true [Lt, 3] link poses at the first filter step (:func:`first_poses`)."""


def first_poses(run_dir: Path, summary: dict[str, Any]) -> FirstPoses:
    """The belief's link poses [Lb, 3] at the run's first filter step and the true link poses
    [Lt, 3] at that step (x m, y m, theta rad); None for a run without filter steps."""
    steps = summary.get("filter_steps") or []
    if not steps:
        return None
    first = steps[0]
    true_pose = episode_true_poses(run_dir, int(first["episode"]))[0]
    n_belief = GaussianBelief.link_count(summary.get("belief") or {})
    return belief_poses([first], range(n_belief))[0], true_pose


def run_links(summary: dict[str, Any], poses: FirstPoses) -> dict[int, int]:
    """Belief link -> true link, nearest at the first filter step (``poses``)."""
    n_belief = GaussianBelief.link_count(summary.get("belief") or {})
    n_true = len(summary["ground_truth"]["object"]["links"])
    if poses is None or n_belief == n_true == 1:
        return {b: b for b in range(min(n_belief, n_true))}
    return match_links(poses[0][:, :2], poses[1][:, :2])


def truth_in_belief_frames(
    truth: dict[str, float], links: dict[int, int], poses: FirstPoses
) -> dict[str, float]:
    """``truth`` with each matched true link's CoM in the frame of its belief link
    (:func:`vistac.objects.com_in_frames`), the frames as they lay at the first filter step
    (``poses``: :func:`first_poses`). Without poses the CoM entries are dropped: the belief's
    frames are unknown, so its CoM cannot be scored."""
    if poses is None:
        return {name: value for name, value in truth.items() if not name.startswith("com_")}
    return com_in_frames(truth, links, poses[0], poses[1])


def mass_and_com(parameters: dict[str, float], poses: np.ndarray) -> tuple[float, float, float]:
    """(total mass kg, combined CoM x m, y m) of links with planar poses [L, 3] (world, x m,
    y m, theta rad) and ``m_i``, ``com_x_i``, ``com_y_i`` (link i's frame) in ``parameters``;
    the CoM is NaN when the masses do not sum to more than 0."""
    masses = np.array([parameters[f"m_{i}"] for i in range(len(poses))])
    coms = np.array([
        to_world_xy(np.array([[parameters[f"com_x_{i}"], parameters[f"com_y_{i}"], 0.0]]),
                    poses[i])[0, :2]
        for i in range(len(poses))
    ])  # fmt: skip
    total = float(masses.sum())
    x, y = masses @ coms / total if total > 0 else (math.nan, math.nan)
    return total, float(x), float(y)


def whole_object(summary: dict[str, Any], poses: FirstPoses) -> dict[str, Any] | None:
    """{"truth", "estimate", "prior"}: :func:`mass_and_com` of the true links, of the final
    belief's means and of the prior's (None without a prior of the belief's links in the
    summary), every link counted, the poses those at the first filter step (``poses``); None
    for a single-link object or a run without filter steps."""
    belief = summary.get("belief") or {}
    if poses is None or len(poses[1]) < 2 or "m_0" not in belief:
        return None

    def means(entries: dict[str, dict[str, float]]) -> dict[str, float]:
        return {name: entry["mean"] for name, entry in entries.items()}

    prior = summary.get("prior") or {}
    links = range(len(poses[0]))
    return {
        "truth": mass_and_com(summary["ground_truth"]["parameters"], poses[1]),
        "estimate": mass_and_com(means(belief), poses[0]),
        "prior": mass_and_com(means(prior), poses[0])
        if all(f"m_{i}" in prior for i in links) else None,
    }


# ---------------------------------------------------------------------------------------------
# Planning the runs


@dataclass(frozen=True)
class EvalOptions:
    """What ``vistac eval`` evaluates: the variants whose model is in ``models``."""

    skill: Path
    out: Path
    objects: tuple[str, ...] = ("test",)
    checkpoints: Path | None = None
    models: tuple[str, ...] = MODELS
    variants: tuple[str, ...] = tuple(
        variant.key for variant in VARIANTS if variant.model not in REPLAY_ONLY_MODELS
    )
    max_objects: int | None = None
    max_interactions: int | None = None
    seed: int | None = None
    overrides: tuple[str, ...] = ()
    paired: bool = False
    """Variants with the first unskipped variant's action selector, and those that do not
    estimate parameters, filter its recorded interactions (``vistac replay``) instead of
    choosing their own."""

    def __post_init__(self) -> None:
        for option, count in (("--max-objects", self.max_objects),
                              ("--max-interactions", self.max_interactions)):  # fmt: skip
            if count is not None and count < 1:
                raise ConfigError(f"{option}: {count} is not a count; give 1 or more")


@dataclass
class RunPlan:
    """One skill run (or the reason it is skipped)."""

    object_path: Path
    spec: ObjectSpec
    variant: Variant
    overrides: list[str] = field(default_factory=list)
    skipped: str | None = None
    lead: RunPlan | None = None
    """With ``paired``: the run whose interactions this one replays."""

    @property
    def model(self) -> str:
        return self.variant.model


def _parse_names(option: str, text: str | Sequence[str], choices: Sequence[str]) -> tuple[str, ...]:
    """``"a,b"`` -> ("a", "b"); a name not in ``choices`` is a ConfigError (exit 2)."""
    names = text.split(",") if isinstance(text, str) else list(text)
    names = [name.strip() for name in names if name.strip()]
    unknown = [name for name in names if name not in choices]
    if unknown or not names:
        what = option.removeprefix("--").removesuffix("s")
        raise ConfigError(
            f"{option}: unknown {what}(s) {', '.join(map(repr, unknown)) or '(none)'}; "
            f"choose from {', '.join(choices)}"
        )
    return tuple(dict.fromkeys(names))


def parse_models(text: str | Sequence[str]) -> tuple[str, ...]:
    """``"gnn,ff"`` -> ("gnn", "ff"); unknown names are a ConfigError (exit 2)."""
    return _parse_names("--models", text, MODELS)


def parse_variants(text: str | Sequence[str]) -> tuple[str, ...]:
    """``"a-gnn,r-gnn"`` -> ("a-gnn", "r-gnn"); unknown names are a ConfigError (exit 2)."""
    return _parse_names("--variants", text, [variant.key for variant in VARIANTS])


def chosen_variants(options: EvalOptions) -> list[Variant]:
    """The variants of ``options.variants`` whose model is in ``options.models``, in table
    order; none left is a ConfigError (exit 2)."""
    chosen = [v for v in VARIANTS if v.key in options.variants and v.model in options.models]
    if not chosen:
        raise ConfigError(
            f"--variants {','.join(options.variants)} with --models "
            f"{','.join(options.models)}: no variant left to evaluate"
        )
    return chosen


def read_skill(skill: Path) -> dict[str, Any]:
    """The skill file as a mapping (safe-loaded), for reading settings before a run; a
    ConfigError (one line) for a file that is missing, malformed or not a mapping."""
    data = read_yaml(skill)
    if not isinstance(data, dict):
        raise ConfigError(f"{skill}: not a skill (a YAML mapping)")
    return data


def skill_prior(skill: Path) -> Prior:
    """The ``prior`` of the skill's ``filters.dual`` component (its defaults when unset)."""
    components = read_skill(skill).get("components") or {}
    for component in components.values():
        if isinstance(component, dict) and component.get("plugin") == "filters.dual":
            try:
                return Prior(**((component.get("with") or {}).get("prior") or {}))
            except (TypeError, ValidationError) as error:
                raise ConfigError(
                    f"{skill}: the filters.dual prior is invalid (each family is [mean, std], "
                    f"e.g. mass_kg: [0.9, 0.4]): {error}"
                ) from None
    return Prior()


def offered_interactions(skill_data: dict[str, Any]) -> set[str]:
    """The interaction kinds (push, pull) the skill's action sampler proposes."""
    components = skill_data.get("components") or {}
    return {
        kind
        for component in components.values()
        if isinstance(component, dict)
        for kind in ((component.get("with") or {}).get("interactions") or [])
    }


def skill_interaction(skill: Path) -> str:
    """The one interaction kind (push or pull) the skill's action sampler proposes."""
    kinds = offered_interactions(read_skill(skill))
    if len(kinds) != 1:
        raise ConfigError(
            f"{skill}: eval needs a skill whose action sampler has exactly one of "
            f"'interactions: [push]' or '[pull]', found {sorted(kinds) or 'none'}"
        )
    return kinds.pop()


def planner_override(selector: str, skill_data: dict[str, Any]) -> str:
    """The ``components.planner=...`` override that selects actions with ``actions.<selector>``.

    A skill whose planner already is that selector keeps its settings; ``actions.info_gain``
    otherwise looks :data:`INFO_GAIN_HORIZON_S` ahead at the skill's ``rate_hz``.
    """
    plugin = f"actions.{selector}"
    planner = (skill_data.get("components") or {}).get("planner")
    component: dict[str, Any] = {"plugin": plugin}
    if isinstance(planner, dict) and planner.get("plugin") == plugin and planner.get("with"):
        component["with"] = dict(planner["with"])
    elif selector == "info_gain":
        rate_hz = _rate_hz(skill_data)
        component["with"] = {"horizon_s": INFO_GAIN_HORIZON_S, "rate_hz": rate_hz}
    return "components.planner=" + json.dumps(component)


def _rate_hz(skill_data: dict[str, Any]) -> float:
    """The skill's ``rate_hz`` (Hz; 15 when unset); a ConfigError when it is no number."""
    rate = skill_data.get("rate_hz", 15.0)
    if isinstance(rate, bool) or not isinstance(rate, int | float):
        raise ConfigError(f"rate_hz: {rate!r} is not a number")
    return float(rate)


def select_objects(selection: Sequence[str], out: Path, max_objects: int | None) -> list[Path]:
    """Object files of the selection (split names or YAML paths), types interleaved."""
    paths: list[Path] = []
    split: dict[str, list[str]] | None = None
    for item in selection:
        if item in SPLITS:
            split = split or write_configurations(OBJECT_SET_SEED, out / "objects")
            paths += interleave_types([out / "objects" / f"{name}.yaml" for name in split[item]])
        else:
            path = Path(item)
            if not path.is_file():
                raise ConfigError(
                    f"--objects: {item!r} is neither a split ({', '.join(SPLITS)}) nor an "
                    "object YAML file"
                )
            paths.append(path.resolve())
    paths = list(dict.fromkeys(paths))
    return paths[:max_objects] if max_objects is not None else paths


def _architecture(checkpoint: Path) -> dict[str, int]:
    sidecar = checkpoint.with_name(checkpoint.name + ".json")
    try:
        return dict(json.loads(sidecar.read_text(encoding="utf-8"))["architecture"])
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def ff_checkpoint(folder: Path, kind: str, n_links: int) -> Path | None:
    """An FF checkpoint for ``n_links`` links: ``ff{n}/ff_{kind}.pt`` or ``ff_{kind}.pt``."""
    for path in (folder / f"ff{n_links}" / f"ff_{kind}.pt", folder / f"ff_{kind}.pt"):
        if path.is_file() and _architecture(path).get("n_links", 1) == n_links:
            return path
    return None


def ff_checkpoints(folder: Path, kind: str) -> dict[int, Path]:
    """Every link count with an FF checkpoint in ``folder`` (:func:`ff_checkpoint`)."""
    found = {n: ff_checkpoint(folder, kind, n) for n in range(1, FF_MAX_LINKS + 1)}
    return {n: path for n, path in found.items() if path is not None}


def model_override(
    model: str, folder: Path, kind: str, learned: dict[str, Any] | None = None
) -> tuple[str | None, str]:
    """The ``components.model=...`` override of ``model``, or (None, why not); ``learned``
    options (:func:`learned_model_options`) go to the GNN and FF models. The FF gets every
    link count's checkpoint in ``folder``: the fitted object's link count picks the net."""
    if model in UNTRAINED_MODELS:
        return "components.model=" + json.dumps({"plugin": UNTRAINED_MODELS[model]}), ""
    if model == "gnn":
        path = folder / f"gnn_{kind}.pt"
        if not path.is_file():
            return None, f"no GNN checkpoint {path}"
        settings: dict[str, Any] = {**(learned or {}), "checkpoint": str(path.resolve())}
    else:
        paths = ff_checkpoints(folder, kind)
        if not paths:
            return None, f"no FF checkpoint in {folder} (ff1/ff_{kind}.pt, ff2/ff_{kind}.pt, ...)"
        path = paths[min(paths)]
        checkpoints = {str(n): str(p.resolve()) for n, p in paths.items()}
        settings = {**(learned or {}), "checkpoints": checkpoints}
    settings |= {k: v for k, v in _architecture(path).items() if k == "hidden"}
    return "components.model=" + json.dumps({"plugin": f"filters.{model}", "with": settings}), ""


def learned_model_options(skill_data: dict[str, Any]) -> dict[str, Any]:
    """The skill's own process-model options that every learned model takes (such as
    ``mirror_average``), less the checkpoint and architecture the variant sets."""
    model = (skill_data.get("components") or {}).get("model") or {}
    shared = set(LearnedModelConfig.model_fields) - {"checkpoint", "hidden"}
    return {key: value for key, value in (model.get("with") or {}).items() if key in shared}


MODEL_OPTION_PREFIX = "components.model.with."
"""``--set`` overrides of the process model's options (applied to every variant's model)."""
PLANNER_OPTION_PREFIX = "components.planner.with."
"""``--set`` overrides of the action selector's options (applied to every variant's)."""


def plan_runs(options: EvalOptions, objects: Sequence[Path], kind: str) -> list[RunPlan]:
    """Every (object, variant) run with its ``--set`` overrides or its skip reason."""
    folder = options.checkpoints or options.skill.parent / "checkpoints"
    # The variant sets the whole model and planner; the user's options of them refine
    # those, after them. The user's other overrides (rate_hz, ...) hold for the variant's.
    model_options, planner_options, common = _split_overrides(options.overrides)
    skill_data = apply_overrides(read_skill(options.skill), list(common))
    learned = learned_model_options(skill_data)
    noise = folder / f"obs_noise_{kind}.pt"
    if noise.is_file():
        common.append(f"components.filter.with.noise_checkpoint={noise.resolve()}")
    if options.max_interactions is not None:
        common.append(f"tree.sequence.1.repeat.max={options.max_interactions}")
    plans = []
    for path in objects:
        spec = load_object(path)
        for variant in chosen_variants(options):
            plan = RunPlan(path, spec, variant)
            model, why = model_override(plan.model, folder, kind, learned)
            if model is None:
                plan.skipped = why
            else:
                planner = planner_override(variant.selector, skill_data)
                plan.overrides = [*common, f"components.world.with.object={path.resolve()}",
                                  model, *model_options, planner,
                                  *planner_options]  # fmt: skip
                if not variant.estimate_parameters:
                    plan.overrides.append("components.filter.with.estimate_parameters=false")
            plans.append(plan)
    if options.paired:
        _pair(plans)
    return plans


def _split_overrides(overrides: Sequence[str]) -> tuple[list[str], list[str], list[str]]:
    """The user's ``--set`` overrides of the process model's options, of the action
    selector's options, and the others."""
    model = [o for o in overrides if o.startswith(MODEL_OPTION_PREFIX)]
    planner = [o for o in overrides if o.startswith(PLANNER_OPTION_PREFIX)]
    other = [o for o in overrides if o not in model and o not in planner]
    return model, planner, other


def _pair(plans: Sequence[RunPlan]) -> None:
    """Per object, let every plan with the first unskipped variant's selector, and every one
    that does not estimate parameters (a replay uses no selector), replay that variant's run
    (``lead``); the others keep their own runs."""
    leads: dict[Path, RunPlan] = {}
    for plan in plans:
        if plan.skipped:
            continue
        lead = leads.setdefault(plan.object_path, plan)
        same_selector = plan.variant.selector == lead.variant.selector
        if lead is not plan and (same_selector or not plan.variant.estimate_parameters):
            plan.lead = lead


# ---------------------------------------------------------------------------------------------
# Running and scoring


def run_dir_of(out: Path, plan: RunPlan) -> Path:
    """Where ``plan``'s run is recorded."""
    return out / "runs" / plan.spec.name / plan.variant.key


def execute(plan: RunPlan, options: EvalOptions) -> dict[str, Any]:
    """Run the skill for ``plan`` (reusing a finished run with the same arguments and the
    same files they name: :func:`vistac.campaign.named_files_digest`).

    KeyboardInterrupt when the run was interrupted: Ctrl-C stops the whole evaluation."""
    from vistac.campaign import args_digest, run_quietly, set_stamp, stamp_of

    run_dir = run_dir_of(options.out, plan)
    args = ["-q", "run", str(options.skill), "--out", str(run_dir), "--overwrite"]
    args += ["--seed", str(options.seed)] if options.seed is not None else []
    for override in plan.overrides:
        args += ["--set", override]
    asked = {"args": args, "inputs": args_digest(args)}
    if stamp_of(run_dir) == asked:
        log.info("reusing %s", run_dir)
        return {"status": "ok", "run_dir": str(run_dir), "exit_code": 0}
    log.info("running %s on %s", plan.variant.label, plan.spec.name)
    set_stamp(run_dir, None)
    code, printed = run_quietly(args)
    log.debug("%s", printed)
    if code != 0:
        return {"status": "failed", "run_dir": str(run_dir), "exit_code": code,
                "reason": f"the skill run exited with {code} (its error is above; a run "
                          f"that started records it in {run_dir})"}  # fmt: skip
    set_stamp(run_dir, asked)
    return {"status": "ok", "run_dir": str(run_dir), "exit_code": 0}


def replay_run(plan: RunPlan, options: EvalOptions) -> dict[str, Any]:
    """Replay ``plan.lead``'s run with ``plan``'s overrides (reusing a finished replay of
    the same lead run: the lead's arguments and summary are part of the replay's stamp)."""
    from vistac.campaign import named_files_digest, set_stamp, stamp_of
    from vistac.pluginmanager import load_plugins
    from vistac.replay import replay

    assert plan.lead is not None
    source, run_dir = run_dir_of(options.out, plan.lead), run_dir_of(options.out, plan)
    lead = stamp_of(source)
    if lead is None:  # stamped once a run has succeeded
        return {"status": "failed", "run_dir": str(run_dir), "exit_code": 1,
                "reason": f"nothing to replay: {plan.lead.variant.label}'s run failed"}  # fmt: skip
    args = {
        "replay": str(source), "overrides": plan.overrides, "lead": lead,
        "lead_summary": hashlib.sha256((source / "summary.json").read_bytes()).hexdigest(),
        "inputs": named_files_digest(options.skill, plan.overrides),
    }  # fmt: skip
    if stamp_of(run_dir) == args:
        log.info("reusing %s", run_dir)
        return {"status": "ok", "run_dir": str(run_dir), "exit_code": 0, "replay_of": str(source)}
    log.info("replaying %s's run on %s with %s", plan.lead.variant.label, plan.spec.name,
             plan.variant.label)  # fmt: skip
    set_stamp(run_dir, None)
    try:
        replay(source, run_dir, load_plugins(), list(plan.overrides), overwrite=True)
    except VistacError as error:
        return {"status": "failed", "run_dir": str(run_dir), "exit_code": error.exit_code,
                "reason": f"replay failed: {error}"}  # fmt: skip
    set_stamp(run_dir, args)
    return {"status": "ok", "run_dir": str(run_dir), "exit_code": 0, "replay_of": str(source)}


def recorded_dir(run_dir: Path) -> Path:
    """The folder whose ``episodes/`` hold ``run_dir``'s interactions: itself, or for a
    ``vistac replay`` folder the run it replayed."""
    if (run_dir / "episodes").is_dir():
        return run_dir
    info = json.loads((run_dir / "run.json").read_text(encoding="utf-8"))
    return Path(info.get("replay_of") or run_dir)


def score_run(run_dir: Path) -> dict[str, Any]:
    """Parameter pairs (final and after each interaction) and tracking errors of one run (or
    replay: its interactions are the replayed run's)."""
    summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    run_dir = recorded_dir(run_dir)
    poses = first_poses(run_dir, summary)
    links = run_links(summary, poses)
    truth = truth_in_belief_frames(summary["ground_truth"]["parameters"], links, poses)
    history = [parameter_pairs(b, truth, links) for b in summary.get("belief_history", [])]
    return {
        "links": {str(b): t for b, t in links.items()},
        "belief_links": GaussianBelief.link_count(summary.get("belief") or {}),
        "interactions": len(summary.get("episodes", [])),
        "parameters": parameter_pairs(summary.get("belief") or {}, truth, links),
        "prior": parameter_pairs(summary["prior"], truth, links) if "prior" in summary else None,
        "normalised_errors": normalised_errors(summary.get("belief") or {}, truth, links),
        "history": history,
        "tracking": tracking_errors(run_dir, summary, links),
        "whole_object": whole_object(summary, poses),
        "joint_bends_rad": largest_bends_rad(run_dir),
    }


def run_record(plan: RunPlan, options: EvalOptions, kind: str) -> dict[str, Any]:
    """Execute and score one planned run; the record eval.json keeps of it."""
    record: dict[str, Any] = {
        "object": plan.spec.name, "object_file": str(plan.object_path), "type": plan.spec.type,
        "kind": kind, "model": plan.model, "variant": plan.variant.label,
        "variant_key": plan.variant.key, "selector": plan.variant.selector,
        "estimate_parameters": plan.variant.estimate_parameters,
    }  # fmt: skip
    if plan.skipped:
        log.info("skipping %s on %s: %s", plan.variant.label, plan.spec.name, plan.skipped)
        return record | {"status": "skipped", "reason": plan.skipped}
    record |= execute(plan, options) if plan.lead is None else replay_run(plan, options)
    if record["status"] == "ok":
        record |= score_run(Path(record["run_dir"]))
    return record


def _scored(records: Sequence[dict[str, Any]], variant: str) -> list[dict[str, Any]]:
    return [r for r in records if r["variant"] == variant and r["status"] == "ok"]


def nrmse_tables(
    records: Sequence[dict[str, Any]], ranges: dict[str, float], variants: Sequence[str]
) -> dict[str, dict[str, dict[str, dict[str, float]]]]:
    """{type: {kind: {variant: {row: NRMSE}}}} of the final beliefs, plus type ``all``."""
    tables: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    for kind_type, kind, variant, runs in _grouped(records, variants, "parameters"):
        cell = tables.setdefault(kind_type, {}).setdefault(kind, {})
        cell[variant] = nrmse_rows(runs, ranges) | {"runs": float(len(runs))}
    return tables


def _grouped(
    records: Sequence[dict[str, Any]], columns: Sequence[str], key: str
) -> Iterator[tuple[str, str, str, list[Any]]]:
    """(object type or ``all``, interaction, column, ``key`` of each of the column's scored
    runs of that type and interaction that has it), for every group with such runs."""
    for kind_type in [*OBJECT_TYPES, "all"]:
        for kind in sorted({r["kind"] for r in records}):
            for column in columns:
                values = [
                    r[key] for r in _scored(records, column)
                    if r["kind"] == kind and kind_type in ("all", r["type"])
                    and r.get(key) is not None
                ]  # fmt: skip
                if values:
                    yield kind_type, kind, column, values


def nrmse_by_interaction(
    records: Sequence[dict[str, Any]], ranges: dict[str, float], variants: Sequence[str]
) -> dict[str, list[float]]:
    """Overall NRMSE after interaction 1, 2, ... per variant (runs that got that far)."""
    curves: dict[str, list[float]] = {}
    for variant in variants:
        runs = _scored(records, variant)
        longest = max((len(r["history"]) for r in runs), default=0)
        curves[variant] = [
            nrmse_rows([r["history"][i] for r in runs if len(r["history"]) > i], ranges)["overall"]
            for i in range(longest)
        ]
    return curves


Differences = dict[str, dict[str, dict[str, dict[str, float]]]]
"""{type: {interaction: {column: difference, low, high, objects}}}."""
BOOTSTRAP_RESAMPLES = 2000
"""Resamples of the objects behind each interval of :func:`difference_table`."""


def _normalised_squares(
    runs: Sequence[Pairs], names: Sequence[str], ranges: dict[str, float]
) -> np.ndarray:
    """[runs, rows] each run's squared error of each row over its range (:func:`nrmse` of the
    one pair); NaN where a run lacks the row."""
    return np.array([
        [nrmse([pairs[name]], ranges[family_of(name)]) ** 2 if name in pairs else np.nan
         for name in names]
        for pairs in runs
    ])  # fmt: skip


def _overall_nrmse(squares: np.ndarray) -> np.ndarray:
    """:func:`nrmse_rows`'s ``overall`` [...] of squared errors [..., runs, rows]: the mean over
    the rows that have a run of the root of their mean."""
    present = ~np.isnan(squares)
    count = present.sum(-2)
    rows = np.sqrt(np.where(present, squares, 0.0).sum(-2) / np.maximum(count, 1))
    scored = count > 0
    return np.where(scored, rows, 0.0).sum(-1) / np.where(scored.any(-1), scored.sum(-1), np.nan)


def resampled_interval(
    statistic: Callable[[np.ndarray], np.ndarray], count: int, seed: int = 0, level: float = 0.9
) -> tuple[float, float]:
    """The ``level`` percentile interval of ``statistic`` over :data:`BOOTSTRAP_RESAMPLES`
    resamples (with replacement, the same under the same ``seed``) of ``count`` items:
    ``statistic`` maps the resampled indices [resamples, count] to one value per resample."""
    draws = np.random.default_rng(seed).integers(0, count, (BOOTSTRAP_RESAMPLES, count))
    low, high = np.nanpercentile(statistic(draws), [50 * (1 - level), 50 * (1 + level)])
    return float(low), float(high)


def overall_difference(
    base: Sequence[Pairs], other: Sequence[Pairs], ranges: dict[str, float],
    seed: int = 0, level: float = 0.9,
) -> dict[str, float]:
    """``other``'s overall NRMSE minus ``base``'s on the same objects (runs paired by index),
    with a ``level`` percentile interval from :data:`BOOTSTRAP_RESAMPLES` resamples of the
    objects (both columns resampled together, so what the objects share cancels; the same
    resamples under the same ``seed``)."""
    names = sorted({name for pairs in (*base, *other) for name in pairs})
    other_squares, base_squares = (
        _normalised_squares(runs, names, ranges) for runs in (other, base)
    )
    count = len(base)
    low, high = resampled_interval(
        lambda draws: _overall_nrmse(other_squares[draws]) - _overall_nrmse(base_squares[draws]),
        count, seed, level,
    )
    difference = _overall_nrmse(other_squares) - _overall_nrmse(base_squares)
    return {"difference": float(difference), "low": float(low), "high": float(high),
            "objects": float(count)}  # fmt: skip


def difference_table(
    records: Sequence[dict[str, Any]], ranges: dict[str, float], columns: Sequence[str],
    seed: int = 0,
) -> Differences:
    """{type: {kind: {column: :func:`overall_difference` against the first column}}}, plus
    type ``all``, over the objects where both columns scored a run; each interval depends on
    its two columns and ``seed`` only."""
    table: Differences = {}
    by_run = {(r["object"], r["kind"], r["variant"]): r for r in records if r["status"] == "ok"}
    for kind_type in [*OBJECT_TYPES, "all"]:
        for kind in sorted({r["kind"] for r in records}):
            for column in columns[1:]:
                pairs = [
                    (by_run[(obj, k, columns[0])]["parameters"], record["parameters"])
                    for (obj, k, variant), record in by_run.items()
                    if k == kind and variant == column and kind_type in ("all", record["type"])
                    and (obj, k, columns[0]) in by_run
                ]  # fmt: skip
                if len(pairs) >= 2:
                    base, other = zip(*pairs, strict=True)
                    cell = table.setdefault(kind_type, {}).setdefault(kind, {})
                    cell[column] = overall_difference(base, other, ranges, seed)
    return table


def whole_object_table(
    records: Sequence[dict[str, Any]], columns: Sequence[str]
) -> dict[str, dict[str, dict[str, dict[str, float]]]]:
    """{type: {kind: {column: RMSE of the total mass (kg) and of the combined CoM (m), runs}}},
    plus type ``all``, over the runs with a :func:`whole_object` score (multi-link objects)."""
    table: dict[str, dict[str, dict[str, dict[str, float]]]] = {}
    for kind_type, kind, column, scores in _grouped(records, columns, "whole_object"):
        error = np.array([np.subtract(score["estimate"], score["truth"]) for score in scores])
        table.setdefault(kind_type, {}).setdefault(kind, {})[column] = {
            "mass_kg": float(np.sqrt(np.mean(error[:, 0] ** 2))),
            "com_m": float(np.sqrt(np.mean(np.sum(error[:, 1:] ** 2, axis=1)))),
            "runs": float(len(scores)),
        }
    return table


def tracking_table(records: Sequence[dict[str, Any]]) -> dict[str, dict[str, dict[str, float]]]:
    """{type: {variant: mean position error (m), angle error (rad), runs}}, plus ``all``."""
    table: dict[str, dict[str, dict[str, float]]] = {}
    for kind_type in [*OBJECT_TYPES, "all"]:
        for variant in dict.fromkeys(r["variant"] for r in records):
            runs = [
                r["tracking"] for r in _scored(records, variant)
                if kind_type in ("all", r["type"]) and r["tracking"]["steps"] > 0
            ]  # fmt: skip
            if runs:
                table.setdefault(kind_type, {})[variant] = {
                    "position_m": float(np.mean([t["position_m"] for t in runs])),
                    "angle_rad": float(np.mean([t["angle_rad"] for t in runs])),
                    "runs": float(len(runs)),
                }
    return table


def calibration_table(
    records: Sequence[dict[str, Any]], ranges: dict[str, float]
) -> dict[str, dict[str, float]]:
    """{variant: share of final normalised errors within +-2 std, their median |z|, the mean
    ``log_score``, count} for the variants that estimate parameters."""
    table: dict[str, dict[str, float]] = {}
    for variant in dict.fromkeys(r["variant"] for r in records if r["estimate_parameters"]):
        entries = [e for r in _scored(records, variant) for e in r["normalised_errors"]]
        if entries:
            z = np.abs([error for _, error, _ in entries])
            scores = [log_score(name, error, std, ranges) for name, error, std in entries]
            table[variant] = {
                "within_2_std": float(np.mean(z <= 2.0)),
                "median_abs_z": float(np.median(z)),
                "log_score": float(np.mean(scores)),
                "entries": float(z.size),
            }
    return table


# ---------------------------------------------------------------------------------------------
# Reports


def _fmt(value: float) -> str:
    return f"{value:.3f}" if math.isfinite(value) else "-"


def differences_markdown(
    differences: Differences, heading: str, meaning: str
) -> list[str]:
    """A section of differences (:func:`difference_table`, :func:`compare_evaluations`) under
    ``heading``, ``meaning`` saying what each is; empty without differences."""
    cells = [(t, k, c, v) for t, by_kind in differences.items() for k, by_column in
             by_kind.items() for c, v in by_column.items()]  # fmt: skip
    if not cells:
        return []
    lines = [f"# {heading}", ""]
    lines += [
        f"{meaning}, with a 90 % interval from resampling those objects {BOOTSTRAP_RESAMPLES} "
        "times; an interval that holds 0 does not rank the two.",
        "",
        "| objects | interaction | column | difference | 90 % interval | runs |",
        "|---|---|---|---:|---|---:|",
    ]
    for kind_type, kind, column, value in cells:
        lines += [f"| {kind_type} | {kind} | {column} | {value['difference']:+.3f} | "
                  f"[{value['low']:+.3f}, {value['high']:+.3f}] | {value['objects']:.0f} |"]
    return [*lines, ""]


_TAGS = ("base", "other")


def compare_evaluations(
    base: Path, other: Path
) -> Differences:
    """{type: {kind: {variant: :func:`overall_difference`}}}: each parameter-estimating
    variant's overall NRMSE in the `vistac eval` folder ``other`` minus in ``base``, paired by
    object (two trainings' checkpoints on the same objects, say). ConfigError when a folder
    holds no evaluation or the two share no variant on two or more objects."""
    reports = [_read_report(folder) for folder in (base, other)]
    variants = [label for label, variant in reports[0]["variants"].items()
                if variant["estimate_parameters"] and label in reports[1]["variants"]]  # fmt: skip
    table: Differences = {}
    for label in variants:
        records = [run | {"variant": tag} for tag, report in zip(_TAGS, reports, strict=True)
                   for run in report["runs"] if run["variant"] == label]  # fmt: skip
        for kind_type, by_kind in difference_table(records, reports[0]["ranges"], _TAGS).items():
            for kind, cells in by_kind.items():
                table.setdefault(kind_type, {}).setdefault(kind, {})[label] = cells["other"]
    if not table:
        raise ConfigError(
            f"{base} and {other} share no parameter-estimating variant run on two or more of "
            "the same objects; compare evaluations of the same objects and variants"
        )
    return table


def _read_report(folder: Path) -> dict[str, Any]:
    path = folder / "eval.json"
    if not path.is_file():
        raise ConfigError(f"{folder}: no eval.json; give the --out folder of a `vistac eval`")
    try:
        report = json.loads(path.read_text(encoding="utf-8"))
    except ValueError as error:
        raise ConfigError(f"{path}: not a `vistac eval` report ({error})") from None
    if isinstance(report, dict) and "records" in report:  # a touch or goal-push campaign
        raise ConfigError(f"{path}: the evaluation of {report.get('skill')}, a touch or "
                          "goal-push skill; `vistac compare` takes two evaluations of a "
                          "parameter-estimation skill")  # fmt: skip
    try:
        return {key: report[key] for key in ("variants", "runs", "ranges")}
    except (KeyError, TypeError) as error:
        raise ConfigError(f"{path}: not a `vistac eval` report (no {error})") from None


def tables_markdown(
    tables: dict[str, dict[str, dict[str, dict[str, float]]]],
    tracking: dict[str, dict[str, dict[str, float]]],
    calibration: dict[str, dict[str, float]] | None = None,
    differences: Differences | None = None,
    differences_from: str = "",
    whole: dict[str, dict[str, dict[str, dict[str, float]]]] | None = None,
) -> str:
    """Markdown NRMSE tables (one per object type and interaction), the differences from the
    first column (:func:`difference_table`), the whole-object (:func:`whole_object_table`),
    the tracking and the calibration tables."""
    lines = ["# Parameter NRMSE (RMSE / range over the object set)", ""]
    lines += [
        "CoM: the distance between the estimated and the true CoM, the truth in the fitted "
        "frame as it lay at the first filter step; its range is that of the radial CoM.",
        "",
        "References on the same objects: *Prior*, the prior's means; *m·f known*, each link's "
        "CoM and the joint friction exact and m and f the best guess from their product, "
        "which is what the force of a quasi-static push shows (about 0.19 for m and 0.22 "
        "for f over the object set's ranges); *load known*, what quasi-static pushes show of "
        "each rigid body, its friction load and where it is centred, exact and the rest the "
        "best guess from them: as *m·f known* for single links and hinged pairs, but of a "
        "welded pair (heterogeneous), or a hinged pair whose hinge held in the run (never "
        f"turned {math.degrees(HELD_BEND_RAD):.0f} deg), only the pair's total load and its "
        "centre (and of a held hinge's friction only a bound: the prior's mean).",
        "",
    ]
    for kind_type, by_kind in tables.items():
        for kind, by_variant in by_kind.items():
            variants = list(by_variant)
            rows = sorted(
                {r for v in by_variant.values() for r in v} - {"overall", "runs"}, key=_row_order
            )
            lines += [f"## {kind_type} objects, {kind}", ""]
            lines += ["| parameter | " + " | ".join(variants) + " |"]
            lines += ["|---|" + "---:|" * len(variants)]
            for row in [*rows, "overall", "runs"]:
                cells = [by_variant[v].get(row, float("nan")) for v in variants]
                text = [f"{c:.0f}" if row == "runs" else _fmt(c) for c in cells]
                lines += [f"| {row} | " + " | ".join(text) + " |"]
            lines += [""]
    lines += differences_markdown(
        differences or {}, f"Differences from {differences_from} (overall NRMSE)",
        f"Each column's overall NRMSE minus {differences_from}'s on the objects both ran "
        f"(negative: lower than {differences_from})",
    )
    lines += whole_object_markdown(whole or {})
    lines += ["# Pose tracking (mean error of the pose change since each episode's start)", ""]
    lines += [
        "| objects | variant | position (mm) | angle (deg) | runs |",
        "|---|---|---:|---:|---:|",
    ]
    for kind_type, by_variant in tracking.items():
        for variant, values in by_variant.items():
            lines += [
                f"| {kind_type} | {variant} | {_fmt(values['position_m'] * 1000)} | "
                f"{_fmt(math.degrees(values['angle_rad']))} | {values['runs']:.0f} |"
            ]
    lines += ["", "# Calibration ((estimate - truth) / std of the final m, f, CoM x/y, f_j)", ""]
    lines += [
        "Log score: the mean negative log likelihood of the true value under each final "
        "Gaussian marginal, std in units of the parameter's range; lower is better, and "
        "a sure but wrong estimate scores worst.",
        "",
    ]
    lines += ["| variant | within 2 std (0.95 if honest) | median abs | log score | entries |",
              "|---|---:|---:|---:|---:|"]  # fmt: skip
    for variant, values in (calibration or {}).items():
        lines += [f"| {variant} | {_fmt(values['within_2_std'])} | "
                  f"{_fmt(values['median_abs_z'])} | {_fmt(values['log_score'])} | "
                  f"{values['entries']:.0f} |"]  # fmt: skip
    return "\n".join(lines) + "\n"


def whole_object_markdown(whole: dict[str, dict[str, dict[str, dict[str, float]]]]) -> list[str]:
    """The whole-object section of tables.md (:func:`whole_object_table`); empty without
    multi-link runs."""
    if not whole:
        return []
    lines = ["# Whole object (RMSE of the total mass and of the combined CoM)", ""]
    lines += [
        "What a push shows of a welded pair: its total mass and its combined CoM, not how "
        "they split between the links. Every link counted; the CoM in the world frame at the "
        "first filter step.",
        "",
        "| objects | interaction | column | mass (kg) | CoM (mm) | runs |",
        "|---|---|---|---:|---:|---:|",
    ]
    for kind_type, by_kind in whole.items():
        for kind, by_column in by_kind.items():
            lines += [f"| {kind_type} | {kind} | {column} | {_fmt(v['mass_kg'])} | "
                      f"{_fmt(v['com_m'] * 1000)} | {v['runs']:.0f} |"
                      for column, v in by_column.items()]  # fmt: skip
    return [*lines, ""]


def plot_curves(curves: dict[str, list[float]], path: Path) -> None:
    """Overall NRMSE vs interaction number, one line per variant (Fig. 12-14)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(5, 3.5))
    for variant, values in curves.items():
        if values:
            axes.plot(range(1, len(values) + 1), values, marker="o", label=variant)
    axes.set_xlabel("interaction")
    axes.set_ylabel("overall NRMSE")
    axes.grid(alpha=0.3)
    if axes.lines:  # no finished run, no line
        axes.legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def belief_series(
    steps: Sequence[dict[str, Any]], link: int
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(mean [T], std [T]) of m, f and the radial CoM (delta-method std) of belief ``link``."""

    def column(name: str, key: str) -> np.ndarray:
        return np.array([step[f"{name}_{link}"][key] for step in steps], dtype=np.float64)

    x, y = column("com_x", "mean"), column("com_y", "mean")
    sx, sy = column("com_x", "std"), column("com_y", "std")
    radius = np.hypot(x, y)
    spread = np.hypot(sx, sy)
    com_std = np.where(
        radius > spread, np.hypot(x * sx, y * sy) / np.maximum(radius, 1e-12), spread
    )
    return {
        "m": (column("m", "mean"), column("m", "std")),
        "f": (column("f", "mean"), column("f", "std")),
        "CoM": (radius, com_std),
    }


def plot_belief(run_dir: Path, record: dict[str, Any], path: Path) -> None:
    """Mean ± 2 std of m, f and the CoM's distance from the fitted frame's origin of belief
    link 0 over time, truth as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    steps = summary.get("filter_steps") or []
    if not steps or "0" not in record["links"]:
        return
    true_link = record["links"]["0"]
    time_s = np.array([step["time_s"] for step in steps], dtype=np.float64)
    figure, axes = plt.subplots(3, 1, figsize=(6, 6), sharex=True)
    units = {"m": "mass (kg)", "f": "friction", "CoM": "CoM from origin (m)"}
    for ax, (family, (mean, std)) in zip(axes, belief_series(steps, 0).items(), strict=True):
        ax.plot(time_s, mean, ".", markersize=2, label="mean")
        ax.fill_between(time_s, mean - 2 * std, mean + 2 * std, alpha=0.3, label="± 2 std")
        if f"{family}_{true_link}" in record["parameters"]:
            truth = record["parameters"][f"{family}_{true_link}"][1]
            ax.axhline(float(np.linalg.norm(truth)), color="k", label="truth")
        ax.set_ylabel(units[family])
    axes[0].set_title(f"{record['object']}: {record['variant']} (belief link 0)")
    axes[0].legend(fontsize=7)
    axes[-1].set_xlabel("time (s)")
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def evaluate(options: EvalOptions) -> dict[str, Any]:
    """Run every planned (object, variant) pair and write tables, plots and eval.json."""
    chosen_variants(options)  # a bad --variants/--models pair fails before anything runs
    prior = skill_prior(options.skill)
    kind = skill_interaction(options.skill)
    refuse_file_as_folder(options.out)
    created = not options.out.exists()
    options.out.mkdir(parents=True, exist_ok=True)
    try:
        objects = select_objects(options.objects, options.out, options.max_objects)
        if not objects:
            raise ConfigError("--objects: no objects selected")
        plans = plan_runs(options, objects, kind)
        check_plans(plans, options.skill)
    except ConfigError:
        if created:  # nothing half-done left behind
            shutil.rmtree(options.out, ignore_errors=True)
        raise
    records = [run_record(plan, options, kind) for plan in plans]
    ranges = parameter_ranges()
    variants = list(dict.fromkeys(plan.variant for plan in plans))
    labels = [variant.label for variant in variants]
    columns = [*(v.label for v in variants if v.estimate_parameters), *REFERENCES]
    scored = [*records, *reference_records(records, prior)]
    report = {
        "skill": str(options.skill), "interaction": kind, "seed": options.seed,
        "objects": [str(p) for p in objects], "models": list(options.models),
        "variants": {v.label: {"model": v.model, "selector": v.selector,
                               "estimate_parameters": v.estimate_parameters} for v in variants},
        "ranges": ranges,
        "ranges_note": "m, f, f_j: the object set's sampling ranges; CoM: range of the radial "
        "CoM over the 120 generated configurations (the CoM error is the distance between "
        "estimate and truth, the truth in the fitted frame at the first filter step)",
        "tables": nrmse_tables(scored, ranges, columns),
        "differences": difference_table(scored, ranges, columns[: columns.index("Prior") + 1]),
        "differences_from": columns[0],
        "whole_object": whole_object_table(scored, columns[: columns.index("Prior") + 1]),
        "nrmse_vs_interactions": nrmse_by_interaction(records, ranges, labels),
        "tracking": tracking_table(records),
        "calibration": calibration_table(records, ranges),
        "runs": records,
    }  # fmt: skip
    _write_reports(report, options.out)
    return report


def check_plans(plans: Sequence[RunPlan], skill: Path) -> None:
    """Validate the skill with each variant's overrides (its first planned run's) before any
    run, so that a bad ``--set`` (say a process-model option the model lacks) fails at once
    with the validation's message, not as every run exiting 2."""
    from vistac.pluginmanager import load_plugins
    from vistac.skill import load_skill

    registry = load_plugins().registry
    checked: set[str] = set()
    for plan in plans:
        if plan.model in REPLAY_ONLY_MODELS and not plan.skipped and plan.lead is None:
            raise ConfigError(
                f"{plan.variant.key} simulates every sigma point and only replays another "
                "variant's interactions: add --paired and a variant before it (e.g. "
                f"--variants a-gnn,{plan.variant.key} --paired)"
            )
        if plan.skipped or plan.variant.key in checked:
            continue
        checked.add(plan.variant.key)
        try:
            load_skill(skill, registry, list(plan.overrides))
        except ConfigError as error:
            raise ConfigError(f"{plan.variant.label}: {error}") from None


def _write_reports(report: dict[str, Any], out: Path) -> None:
    (out / "eval.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    (out / "tables.json").write_text(
        json.dumps({key: report[key] for key in ("ranges", "tables", "differences",
                                                   "differences_from", "whole_object",
                                                   "tracking", "calibration",
                                                   "nrmse_vs_interactions")},
                   indent=2),
        encoding="utf-8",
    )  # fmt: skip
    markdown = tables_markdown(
        report["tables"], report["tracking"], report["calibration"], report["differences"],
        report["differences_from"], report["whole_object"],
    )
    (out / "tables.md").write_text(markdown, encoding="utf-8")
    plot_curves(report["nrmse_vs_interactions"], out / "nrmse_vs_interactions.png")
    for record in report["runs"]:
        if record["status"] == "ok":
            name = f"belief_{record['object']}_{record['variant_key']}.png"
            plot_belief(Path(record["run_dir"]), record, out / name)
