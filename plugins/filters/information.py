"""What the simulator shows of an object's parameters through the pushes a run made.

Each recorded push of a simulated run is replayed in the MuJoCo world from its recorded start
(the links at their recorded poses, at rest; the gripper along its recorded path) and cut into
windows of :data:`WINDOW_STEPS` control steps, as the process models are trained and scored.
Per window the outcome is each link's change of pose (x, y, theta) and the mean finger force
(x, y); central differences, each window started from the replay's own state, give its
Jacobian with respect to every parameter (m, f, CoM per link; the joint friction of a hinge).

A process model that moved with the parameters exactly as the simulator does, and erred by a
:class:`ModelError` on each window independently, would learn from these pushes at best the
Bayes posterior of the linearised problem: ``P = (P0^-1 + J^T R^-1 J)^-1`` with ``P0`` the
covariance of the object set's sampling distributions (:mod:`vistac.objects`) and ``R`` the
squared model error on the diagonal. Its diagonal, over the runs and normalised by the parameter
ranges as ``vistac eval`` normalises, is the expected NRMSE of that model: what the pushes show
at that model error. It is a local figure, at the true parameters: a hinge whose friction holds
it still through a push shows only that its friction is above what the push asked of it, and
counts as showing nothing. Where a model's errors repeat from window to window (a share of
each is the same error, in each push's frame, on every push of an object:
``ModelError.repeated``), ``R`` holds that share across windows (:func:`noise_covariance`):
a repeated push then shows nothing new, while pushes in other directions can tell the
repeated error apart from the parameters.
"""

from __future__ import annotations

import json
import logging
import math
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import torch
from vistac.errors import ConfigError, DataError
from vistac.objects import (
    COM_SHRINK,
    FRICTION_RANGE,
    JOINT_FRICTION_RANGE_NM,
    MASS_RANGE_KG,
    ObjectSpec,
    polygon_centroid_covariance,
    redraw_parameters,
)
from vistac.pluginmanager import Plugins
from vistac.plugins.filters.data import (
    Trajectory,
    central_twist,
    load_trajectories,
    process_inputs,
    too_fast_a_turn,
    true_states,
    unwrap_theta,
)
from vistac.plugins.filters.evaluate import family_of, parameter_ranges
from vistac.plugins.filters.state import DTYPE, StateLayout
from vistac.plugins.hardware.sim.object_sim import ObjectSim
from vistac.skill import load_skill
from vistac.testing import build_components
from vistac.types import FloatArray

log = logging.getLogger(__name__)

WINDOW_STEPS = 25
"""Control steps per window: the training's rollout length (``rollout_steps``)."""
MIN_WINDOW_STEPS = 10
"""A push's last, shorter window is kept when it has at least this many steps."""
FINITE_STEP = {"m": 0.2, "f": 0.08, "com_x": 0.012, "com_y": 0.012, "f_j": 0.12}
"""Half the central-difference step per parameter family (kg, -, m, m, N m), a seventh to a
fifth of each range: the simulator's contacts make the change of a push uneven at smaller
steps (the columns of one push from steps a quarter this size pointed apart, cosine down to
-0.36 between 0.05 and 0.025 kg), while from these to steps twice as large they agree
(cosine 0.8-1.0)."""
BOUNDS = {"m": MASS_RANGE_KG, "f": FRICTION_RANGE, "f_j": JOINT_FRICTION_RANGE_NM}
"""Where a step stops: the sampling ranges of the object set (a mass of 0 cannot be
simulated)."""


@dataclass(frozen=True)
class ModelError:
    """A process model's error per window: each link's position (m) and angle (rad), and
    the mean finger force (N) along each axis."""

    position_m: float = 0.007
    angle_rad: float = math.radians(2.5)
    force_n: float = 0.8
    repeated: float = 0.0
    """The share of each window's error that is one error of the object's, the same in
    every push's frame (:func:`noise_covariance`); 0: independent from window to window."""

    def per_window(self, n_links: int) -> FloatArray:
        """Standard deviations [3 L + 2] in the order of a window's outcome."""
        link = [self.position_m, self.position_m, self.angle_rad]
        return np.array(link * n_links + [self.force_n] * 2)

    def scaled(self, factor: float) -> ModelError:
        return ModelError(
            self.position_m * factor, self.angle_rad * factor, self.force_n * factor,
            self.repeated,
        )


DEFAULT_ERROR = ModelError()
"""About the shipped push GNN's error 25 steps ahead from the true states of the test pushes:
7.1 mm and 2.5 deg on articulated objects, 8.8 mm and 3.1 deg on heterogeneous ones, and its
one-step finger force error 0.76 N and 1.34 N (docs/results.md)."""


@dataclass(frozen=True)
class RecordedPush:
    """One recorded push: time_s [T]; arm_pose [T, 4] (x, y, z m, yaw rad); object_pose
    [T, L, 3] (x, y m, theta rad per link, true)."""

    spec: ObjectSpec
    time_s: FloatArray
    arm_pose: FloatArray
    object_pose: FloatArray
    pd_rad: float = 0.0
    """The push's direction in the world."""

    @classmethod
    def read(cls, folder: Path) -> RecordedPush | None:
        """The push recorded in an episode folder; None for a pull or a push too short for a
        window."""
        meta = json.loads((folder / "meta.json").read_text(encoding="utf-8"))
        truth = meta.get("ground_truth") or {}
        if "object" not in truth:
            raise DataError(f"{folder}: no ground truth; only simulated runs can be replayed")
        if meta.get("action", {}).get("kind") != "push":
            return None
        with np.load(folder / "data.npz") as data:
            if "object_pose" not in data.files:
                return None
            push = cls(ObjectSpec.model_validate(truth["object"]), data["time_s"],
                       data["arm_pose"], data["object_pose"],
                       float(meta["action"].get("pd_rad", 0.0)))  # fmt: skip
        return push if len(push.time_s) > MIN_WINDOW_STEPS else None


def first_window_steps(steps: int) -> list[int]:
    """The first step of each window of a push of ``steps`` recorded steps."""
    return [step for step in range(0, steps - 1, WINDOW_STEPS)
            if steps - 1 - step >= MIN_WINDOW_STEPS]  # fmt: skip


def parameter_names(spec: ObjectSpec) -> tuple[str, ...]:
    """The parameters a replay varies, in its order: m, f, com_x, com_y per link, then the
    hinge's f_j_0 (a welded pair's joint has none)."""
    names = [f"{key}_{i}" for i in range(len(spec.links)) for key in ("m", "f", "com_x", "com_y")]
    return tuple(names + (["f_j_0"] if spec.joint is not None else []))


class PushReplay(ObjectSim):
    """The simulated world of one object, replaying recorded pushes with the parameters set
    between replays (:meth:`ObjectSim.set_parameters`, in :attr:`names` order)."""

    def __init__(self, spec: ObjectSpec) -> None:
        super().__init__(spec)
        self.names = parameter_names(spec)
        self.truth = np.array([spec.parameters()[name] for name in self.names])
        self._state = mujoco.mjtState.mjSTATE_INTEGRATION

    def start(self, push: RecordedPush) -> None:
        """The world at the push's first recorded step: links at rest at their poses, the
        gripper at its pose with the fingers closed."""
        theta = push.object_pose[0, 0, 2]
        hinge = push.object_pose[0, 1, 2] - theta if self.hinge is not None else 0.0
        self.place(push.object_pose[0, 0], hinge, push.arm_pose[0])

    def advance(self, push: RecordedPush, step: int) -> None:
        """Control step ``step`` -> ``step + 1``, the gripper at the recorded velocity
        (:meth:`ObjectSim.drive`)."""
        dt_s = float(push.time_s[step + 1] - push.time_s[step])
        velocity = (push.arm_pose[step + 1] - push.arm_pose[step]) / dt_s
        self.drive(push.arm_pose[step], velocity, dt_s)

    def run(
        self, push: RecordedPush, values: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray]:
        """The whole push replayed with ``values`` (default: the true parameters): link
        poses [T, L, 3] and the finger force [T, 2] at each recorded step."""
        self.set_parameters(self.truth if values is None else values)
        self.start(push)
        poses, forces = [self.link_poses()], [self.finger_force_n()]
        for step in range(len(push.time_s) - 1):
            self.advance(push, step)
            poses.append(self.link_poses())
            forces.append(self.finger_force_n())
        return np.array(poses), np.array(forces)

    def window_starts(self, push: RecordedPush) -> list[tuple[int, FloatArray]]:
        """(step, simulator state) at the start of each window of the true replay."""
        self.set_parameters(self.truth)
        self.start(push)
        starts = []
        size = mujoco.mj_stateSize(self.model, self._state)
        first_steps = first_window_steps(len(push.time_s))
        for step in range(len(push.time_s) - 1):
            if step in first_steps:
                state = np.empty(size)
                mujoco.mj_getState(self.model, self.data, state, self._state)
                starts.append((step, state))
            self.advance(push, step)
        return starts

    def window_outcome(
        self, push: RecordedPush, start: tuple[int, FloatArray], values: FloatArray
    ) -> FloatArray:
        """From a window's start with ``values``: each link's change of pose and the mean
        finger force, [3 L + 2]."""
        step, state = start
        self.set_parameters(values)
        mujoco.mj_setState(self.model, self.data, state, self._state)
        mujoco.mj_forward(self.model, self.data)
        before = self.link_poses()
        stop = min(step + WINDOW_STEPS, len(push.time_s) - 1)
        forces = []
        for k in range(step, stop):
            self.advance(push, k)
            forces.append(self.finger_force_n())
        change = self.link_poses() - before
        change[:, 2] = np.angle(np.exp(1j * change[:, 2]))
        return np.concatenate([change.ravel(), np.mean(forces, axis=0)])


def finite_points(names: Sequence[str], values: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The parameter values [P, P] a central difference evaluates, one row per parameter
    moved up and one moved down by its :data:`FINITE_STEP`, within :data:`BOUNDS`."""
    up, down = np.tile(values, (len(names), 1)), np.tile(values, (len(names), 1))
    for j, name in enumerate(names):
        low, high = BOUNDS.get(family_of(name), (-np.inf, np.inf))
        up[j, j] = min(values[j] + FINITE_STEP[family_of(name)], high)
        down[j, j] = max(values[j] - FINITE_STEP[family_of(name)], low)
    return up, down


def push_jacobian(replay: PushReplay, push: RecordedPush) -> FloatArray:
    """d(window outcome)/d(parameters) of every window of a push: [W (3 L + 2), P]."""
    up, down = finite_points(replay.names, replay.truth)
    blocks = []
    for start in replay.window_starts(push):
        columns = [(replay.window_outcome(push, start, high)
                    - replay.window_outcome(push, start, low)) / (high[j] - low[j])
                   for j, (high, low) in enumerate(zip(up, down, strict=True))]  # fmt: skip
        blocks.append(np.array(columns).T)
    return np.concatenate(blocks)


def prior_covariance(spec: ObjectSpec) -> FloatArray:
    """Covariance [P, P] of the object set's sampling distributions at this object's links:
    m, f and f_j uniform over their ranges, each CoM uniform in its footprint shrunk by
    :data:`vistac.objects.COM_SHRINK`."""
    names = parameter_names(spec)
    cov = np.zeros((len(names), len(names)))
    for i, link in enumerate(spec.links):
        row = 4 * i
        cov[row, row] = (MASS_RANGE_KG[1] - MASS_RANGE_KG[0]) ** 2 / 12
        cov[row + 1, row + 1] = (FRICTION_RANGE[1] - FRICTION_RANGE[0]) ** 2 / 12
        cov[row + 2 : row + 4, row + 2 : row + 4] = polygon_centroid_covariance(
            COM_SHRINK * link.polygon()
        )[1]
    if spec.joint is not None:
        cov[-1, -1] = (JOINT_FRICTION_RANGE_NM[1] - JOINT_FRICTION_RANGE_NM[0]) ** 2 / 12
    return cov


def posterior_covariance(
    jacobian: FloatArray, prior: FloatArray, noise: FloatArray
) -> FloatArray:
    """``(P0^-1 + J^T R^-1 J)^-1``: jacobian [N, P], prior [P, P], noise the standard
    deviations [N] (R their squares on the diagonal) or R itself [N, N], which may be
    singular (an error repeated whole), as ``P0 - P0 J^T (J P0 J^T + R)^+ J P0``. Returns
    [P, P]."""
    if noise.ndim == 2:
        spread = jacobian @ prior  # [N, P]
        innovation = np.linalg.pinv(spread @ jacobian.T + noise, hermitian=True)
        return np.asarray(prior - spread.T @ innovation @ spread)
    weighted = jacobian / noise[:, None] ** 2
    return np.asarray(np.linalg.inv(np.linalg.inv(prior) + jacobian.T @ weighted))


def noise_covariance(
    error: ModelError, n_links: int, windows_rad: Sequence[float]
) -> FloatArray:
    """The covariance R [W (3 L + 2), W (3 L + 2)] of a model's errors over one object's W
    windows, each pushed in direction ``windows_rad`` [W]: a share ``error.repeated`` of each
    window's error is one error of the object's, the same in every push's frame (each link's
    position and the force turned by the push's direction; the angles as they are); the rest
    is independent from window to window. With ``repeated`` 0, ``diag(per_window^2)``."""
    std = error.per_window(n_links)
    size = len(std)
    turns = np.zeros((len(windows_rad), size, size))
    for w, angle in enumerate(windows_rad):
        cos, sin = math.cos(angle), math.sin(angle)
        turns[w] = np.eye(size)
        for first in [3 * link for link in range(n_links)] + [3 * n_links]:
            turns[w, first : first + 2, first : first + 2] = [[cos, -sin], [sin, cos]]
    stacked = turns.reshape(-1, size)  # push frame -> world, per window: [W D, D]
    shared = stacked @ np.diag(std**2) @ stacked.T
    own = np.diag(np.tile(std**2, len(windows_rad)))
    return np.asarray((1.0 - error.repeated) * own + error.repeated * shared)


def squared_errors(names: Sequence[str], cov: FloatArray) -> dict[str, float]:
    """Expected squared error per table row (``m_0``, ``CoM_0`` = com_x + com_y, ``f_j_0``)
    of a Bayes estimate with posterior covariance ``cov`` [P, P]."""
    rows: dict[str, float] = {}
    for j, name in enumerate(names):
        key, link = name.rsplit("_", 1)
        row = f"CoM_{link}" if key.startswith("com_") else name
        rows[row] = rows.get(row, 0.0) + float(cov[j, j])
    return rows


@dataclass(frozen=True)
class ObjectInformation:
    """A run's pushes (their episode folders) and each one's Jacobian [W (3 L + 2), P]."""

    spec: ObjectSpec
    folders: list[Path]
    jacobians: list[FloatArray]
    directions_rad: list[float]
    """Each push's direction."""

    @property
    def jacobian(self) -> FloatArray:
        """Every push's windows: [sum W (3 L + 2), P]."""
        return np.concatenate(self.jacobians)

    def squared_errors(self, error: ModelError) -> dict[str, float]:
        n_links = len(self.spec.links)
        windows = [angle for angle, jacobian in zip(self.directions_rad, self.jacobians,
                                                    strict=True)
                   for _ in range(len(jacobian) // (3 * n_links + 2))]  # fmt: skip
        if error.repeated:
            noise = noise_covariance(error, n_links, windows)
        else:
            noise = np.tile(error.per_window(n_links), len(windows))
        cov = posterior_covariance(self.jacobian, prior_covariance(self.spec), noise)
        return squared_errors(parameter_names(self.spec), cov)


def run_information(run_dir: Path) -> ObjectInformation | None:
    """The Jacobian of every push a simulated run recorded; None when it recorded none."""
    folders = sorted(p for p in (run_dir / "episodes").glob("*") if (p / "meta.json").is_file())
    pushes = [(folder, push) for folder in folders
              if (push := RecordedPush.read(folder)) is not None]  # fmt: skip
    if not pushes:
        return None
    replay = PushReplay(pushes[0][1].spec)
    return ObjectInformation(pushes[0][1].spec, [folder for folder, _ in pushes],
                             [push_jacobian(replay, push) for _, push in pushes],
                             [push.pd_rad for _, push in pushes])  # fmt: skip


def expected_nrmse_rows(
    objects: Iterable[ObjectInformation], error: ModelError, ranges: dict[str, float]
) -> dict[str, float]:
    """Expected NRMSE per row over the objects (RMS over them, normalised by the family's
    range) and ``overall`` (the mean of the rows), as ``vistac eval``'s tables."""
    collected: dict[str, list[float]] = {}
    for info in objects:
        for row, value in info.squared_errors(error).items():
            collected.setdefault(row, []).append(value)
    rows = {row: math.sqrt(float(np.mean(values))) / ranges[family_of(row)]
            for row, values in collected.items()}  # fmt: skip
    rows["overall"] = float(np.mean(list(rows.values())))
    return rows


def run_folders(folder: Path, variant: str) -> list[Path]:
    """The run folders under ``folder``: itself when it is a run (``episodes/``), else a
    ``vistac eval`` folder's ``runs/*/VARIANT``."""
    if (folder / "episodes").is_dir():
        return [folder]
    runs = sorted(p for p in (folder / "runs").glob(f"*/{variant}") if (p / "episodes").is_dir())
    if not runs:
        raise ConfigError(
            f"{folder}: neither a run folder (with episodes/) nor a `vistac eval` folder with "
            f"runs/*/{variant}/episodes; give a run's or an evaluation's --out folder, and "
            f"--variant the column whose pushes to replay"
        )
    return runs


def collect_information(runs: Sequence[Path]) -> dict[str, list[ObjectInformation]]:
    """:func:`run_information` of every run, by object type; DataError when no run recorded
    a push."""
    by_type: dict[str, list[ObjectInformation]] = {}
    for run in runs:
        info = run_information(run)
        if info is None:
            log.warning("%s: no push to replay (pulls are not replayed)", run)
            continue
        by_type.setdefault(info.spec.type, []).append(info)
    if not by_type:
        raise DataError("no run recorded a push: only pushes are replayed")
    return by_type


def information_tables(
    by_type: dict[str, list[ObjectInformation]],
    error: ModelError,
    scales: Sequence[float],
    own: dict[str, ModelError] | None = None,
) -> dict[str, dict[str, dict[str, float]]]:
    """{object type: {"x SCALE": {row: expected NRMSE, "overall", "runs"}}} at ``error``
    times each scale, and at a model's own error on that type (``own``): row "own" with its
    errors independent from window to window, and where they repeat (``repeated`` above
    0) row "own, repeating" as they do."""
    ranges = parameter_ranges()
    tables: dict[str, dict[str, dict[str, float]]] = {}
    for kind, infos in by_type.items():
        errors = {f"x {scale:g}": error.scaled(scale) for scale in scales}
        if own is not None and kind in own:
            errors["own"] = replace(own[kind], repeated=0.0)
            if own[kind].repeated > 0:
                errors["own, repeating"] = own[kind]
        runs = {"runs": float(len(infos))}
        tables[kind] = {label: expected_nrmse_rows(infos, value, ranges) | runs
                        for label, value in errors.items()}  # fmt: skip
    return tables


def repeated_share(errors: Sequence[tuple[FloatArray, float]], weights: FloatArray) -> float:
    """How much a model's window errors on one object repeat: the share of their squared size
    that their mean carries (1 / W for errors independent from window to window, 1 for one
    error repeated). ``errors``: per push (error [W, 3 L + 2], its push direction, rad), each
    link's position and the force turned into the push's frame; ``weights`` [3 L + 2]: the
    scale of each outcome (a model error's :meth:`ModelError.per_window`)."""
    turned = []
    for error, pd_rad in errors:
        cos, sin = math.cos(pd_rad), math.sin(pd_rad)
        to_push = np.array([[cos, -sin], [sin, cos]])  # row vectors: (x, y) @ to_push
        frame = np.array(error, dtype=float)
        n_links = (frame.shape[1] - 2) // 3
        for first in [3 * link for link in range(n_links)] + [3 * n_links]:
            frame[:, first : first + 2] = frame[:, first : first + 2] @ to_push
        turned.append(frame / weights)
    windows = np.concatenate(turned)
    return float(np.sum(windows.mean(axis=0) ** 2) / np.sum(np.mean(windows**2, axis=0)))


@dataclass(frozen=True)
class ModelReport:
    """How a process model did on one object type's windows: its :func:`sensitivity_agreement`
    with the simulator and its own RMS error at the true parameters."""

    agreement: dict[str, dict[str, float]]
    error: ModelError
    repeated_share: float
    """:func:`repeated_share` of the errors, the mean over the objects."""
    independent_share: float
    """What it would be for errors independent from window to window: the mean of 1 / W."""

    @property
    def repeating_error(self) -> ModelError:
        """:attr:`error` with the share of it that repeats beyond chance: ``repeated`` =
        (repeated share - independent share) / (1 - independent share), at least 0."""
        excess = (self.repeated_share - self.independent_share) / (1 - self.independent_share)
        return replace(self.error, repeated=max(0.0, excess))


def model_reports(
    by_type: dict[str, list[ObjectInformation]], model: Any, error: ModelError
) -> dict[str, ModelReport]:
    """{object type: ``model`` on its runs' pushes}; ``error`` weighs the outcomes for the
    agreement."""
    reports = {}
    for kind, infos in by_type.items():
        pairs, errors, shares, independent = [], [], [], []
        for info in infos:
            recorded = {t.source: t for t in load_trajectories([info.folders[0].parent.parent])}
            names, n_links = parameter_names(info.spec), len(info.spec.links)
            own_errors = []
            for folder, sim in zip(info.folders, info.jacobians, strict=True):
                trajectory = recorded.get(str(folder))
                if trajectory is not None:
                    jacobian, own = model_jacobian(model, trajectory, names)
                    pairs.append((jacobian, sim, n_links))
                    errors.append((own, n_links))
                    own_errors.append((own, trajectory.pd_rad))
            if own_errors:
                shares.append(repeated_share(own_errors, error.per_window(n_links)))
                independent.append(1 / sum(len(own) for own, _ in own_errors))
        reports[kind] = ModelReport(
            sensitivity_agreement(pairs, parameter_names(infos[0].spec), error),
            measured_error(errors), float(np.mean(shares)), float(np.mean(independent)),
        )
    return reports


def information_markdown(
    tables: dict[str, dict[str, dict[str, float]]], error: ModelError
) -> list[str]:
    """The tables as markdown: per object type, a row per model-error scale."""
    lines = [
        "# What the pushes show (expected NRMSE at a model error)",
        "",
        f"A process model that moved with the parameters as the simulator does and erred per "
        f"{WINDOW_STEPS}-step window by {error.position_m * 1e3:.1f} mm, "
        f"{math.degrees(error.angle_rad):.1f} deg and {error.force_n:.2f} N (times the scale): "
        "the linearised Bayes posterior of the parameters from these pushes.",
    ]
    for kind, scales in tables.items():
        rows = [row for row in next(iter(scales.values())) if row not in ("overall", "runs")]
        lines += ["", f"## {kind} objects", "",
                  "| model error | " + " | ".join(rows) + " | overall | runs |",
                  "|---|" + "---:|" * (len(rows) + 2)]  # fmt: skip
        for scale, values in scales.items():
            cells = [f"{values[row]:.3f}" for row in [*rows, "overall"]]
            lines.append(f"| {scale} | " + " | ".join(cells) + f" | {values['runs']:.0f} |")
    return lines


def model_markdown(reports: dict[str, ModelReport]) -> list[str]:
    """Per object type, the model's own error and, per parameter, the cosine and length ratio
    of its sensitivity against the simulator's."""
    lines = ["", "# How the process model moves with the parameters (against the simulator)", "",
             "Its error at the true parameters per window (the row \"own\" above is what the "
             "pushes show at that error); then per parameter the cosine between the model's and "
             "the simulator's change of the window outcomes per unit of the parameter (1: the "
             "same direction), and the ratio of their lengths (1: as much), every outcome in "
             "units of the model error of the first table."]  # fmt: skip
    for kind, report in reports.items():
        rows, own = report.agreement, report.error
        lines += ["", f"## {kind} objects", "",
                  f"Own error: {own.position_m * 1e3:.1f} mm, "
                  f"{math.degrees(own.angle_rad):.2f} deg, {own.force_n:.2f} N. The mean of an "
                  f"object's window errors (each push's frame) carries "
                  f"{report.repeated_share:.0%} of their squared size "
                  f"({report.independent_share:.0%} if they were independent: the row "
                  "\"own\" assumes that; where they repeat more, \"own, repeating\" takes "
                  "them as they do).", "",
                  "| | " + " | ".join(rows) + " |", "|---|" + "---:|" * len(rows)]  # fmt: skip
        for key, label in (("cosine", "cosine"), ("length_ratio", "length ratio")):
            lines.append(f"| {label} | " + " | ".join(f"{v[key]:.2f}" for v in rows.values())
                         + " |")  # fmt: skip
    return lines


def replayed_pushes(
    trajectories: Sequence[Trajectory], count: int, rng: np.random.Generator
) -> list[Trajectory]:
    """Each recorded push of ``trajectories`` replayed ``count`` times from its recorded
    start along its recorded path, each time with the object's parameters drawn anew
    (:func:`vistac.objects.redraw_parameters`): the same push on objects that differ only in
    their parameters. A replay whose object tipped over is left out."""
    replayed: list[Trajectory] = []
    for trajectory in trajectories:
        if trajectory.kind != "push" or trajectory.reflected:
            continue
        push = RecordedPush.read(Path(trajectory.source))
        if push is None:
            continue
        replay = PushReplay(push.spec)
        for _ in range(count):
            spec = redraw_parameters(push.spec, rng)
            values = np.array([spec.parameters()[name] for name in replay.names])
            poses, force_n = replay.run(push, values)
            poses = unwrap_theta(poses)
            if too_fast_a_turn(poses, trajectory.dt_s):
                continue
            replayed.append(replace(
                trajectory, source=f"{trajectory.source} (replayed)", spec=spec, poses=poses,
                twists=central_twist(poses, trajectory.dt_s), force_n=force_n, depth_m=None,
                camera_pose=None, parameters=spec.parameters(),
            ))  # fmt: skip
    return replayed


def model_jacobian(
    model: Any, trajectory: Trajectory, names: Sequence[str]
) -> tuple[FloatArray, FloatArray]:
    """d(window outcome)/d(parameters ``names``) of a process model: each window rolled out
    open loop from the recorded true state at its start, as the simulator's windows are
    replayed (:func:`push_jacobian`), and the model's error at the true parameters. Returns
    (jacobian [W (3 L + 2), P], error [W, 3 L + 2] = the model's outcome minus the recorded
    one)."""
    layout = StateLayout(trajectory.n_links)
    states = true_states(trajectory, layout)
    inputs = process_inputs([trajectory])
    rows = [layout.index(name) for name in names]
    blocks, errors = [], []
    for first in first_window_steps(trajectory.steps):
        stop = min(first + WINDOW_STEPS, trajectory.steps - 1)
        up, down = finite_points(names, states[first, rows].numpy())
        batch = states[first].repeat(2 * len(rows) + 1, 1)  # up, down per parameter; truth
        batch[0:-1:2, rows] = torch.as_tensor(up, dtype=DTYPE)
        batch[1:-1:2, rows] = torch.as_tensor(down, dtype=DTYPE)
        x, forces = batch[None], []
        with torch.no_grad():
            for step in range(first, stop):
                prediction = model.predict(x, inputs[step], trajectory.dt_s)
                forces.append(prediction.force_n[0])
                x = torch.cat([prediction.pose, x[..., layout.n_pose :]], -1)
        change = (layout.link_pose(x[0]) - layout.link_pose(batch))[..., :3].numpy()
        outcome = np.concatenate([_wrapped(change).reshape(len(batch), -1),
                                  torch.stack(forces).mean(0).numpy()], 1)  # fmt: skip
        spans = np.diag(up - down)
        blocks.append(((outcome[0:-1:2] - outcome[1:-1:2]) / spans[:, None]).T)
        recorded = np.concatenate([
            _wrapped(trajectory.poses[stop] - trajectory.poses[first]).ravel(),
            trajectory.force_n[first + 1 : stop + 1].mean(axis=0),
        ])  # fmt: skip
        errors.append(outcome[-1] - recorded)
    return np.concatenate(blocks), np.array(errors)


def _wrapped(change: FloatArray) -> FloatArray:
    """A change of poses [..., 3] with its angle wrapped to (-pi, pi] (a copy)."""
    wrapped = np.array(change, dtype=float)
    wrapped[..., 2] = np.angle(np.exp(1j * wrapped[..., 2]))
    return wrapped


def measured_error(errors: Sequence[tuple[FloatArray, int]]) -> ModelError:
    """The RMS model error of windows: ``errors`` holds (error [W, 3 L + 2], L) per push;
    position over every link's x and y, angle over every link's, force over both axes."""
    position = np.concatenate([e[:, : 3 * n].reshape(-1, n, 3)[..., :2].ravel()
                               for e, n in errors])  # fmt: skip
    angle = np.concatenate([e[:, : 3 * n].reshape(-1, n, 3)[..., 2].ravel() for e, n in errors])
    force = np.concatenate([e[:, 3 * n :].ravel() for e, n in errors])
    def rms(values: FloatArray) -> float:
        return float(np.sqrt(np.mean(np.square(values))))

    return ModelError(rms(position), rms(angle), rms(force))


def sensitivity_agreement(
    pairs: Sequence[tuple[FloatArray, FloatArray, int]], names: Sequence[str], error: ModelError
) -> dict[str, dict[str, float]]:
    """How a process model's sensitivities match the simulator's: per parameter, over every
    window of ``pairs`` (model Jacobian, simulator Jacobian, link count), the cosine between
    the two columns and the ratio of their lengths, each outcome in units of its model error
    (1: the model moves with the parameter as the simulator does)."""
    agreement = {}
    for j, name in enumerate(names):
        model_column = np.concatenate(
            [m[:, j] / np.tile(error.per_window(n), len(m) // (3 * n + 2)) for m, _, n in pairs]
        )
        sim_column = np.concatenate(
            [s[:, j] / np.tile(error.per_window(n), len(s) // (3 * n + 2)) for _, s, n in pairs]
        )
        lengths = float(np.linalg.norm(model_column)), float(np.linalg.norm(sim_column))
        agreement[name] = {
            "cosine": float(model_column @ sim_column / max(lengths[0] * lengths[1], 1e-300)),
            "length_ratio": float(lengths[0] / max(lengths[1], 1e-300)),
        }
    return agreement


def skill_model(skill: Path, overrides: list[str], plugins: Plugins) -> Any:
    """The process model (``components.model``) of a skill file with ``overrides``."""
    loaded = load_skill(skill, plugins.registry, overrides)
    block = loaded.raw.get("components", {}).get("model")
    if block is None:
        raise ConfigError(f"{skill}: the skill has no components.model to compare")
    with tempfile.TemporaryDirectory() as scratch:
        return build_components({"model": block}, Path(scratch), seed=loaded.seed,
                                skill_dir=loaded.skill_dir, plugins=plugins).component("model")
