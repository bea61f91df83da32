"""One ``typing.Protocol`` per component kind.

A plugin's component implements the protocol of its kind; ``vistac.testing`` checks that an
implementation behaves as the protocol says. Simulated and real devices implement the same
protocols, so a skill swaps one for the other in YAML only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
from vistac.types import (
    RGBD,
    Action,
    ArmState,
    FloatArray,
    GaussianBelief,
    GripperState,
    PixelWindow,
    PointCloud,
    ShapeEstimate,
    TactileReading,
    Viewpoint,
)

KINDS: tuple[str, ...] = (
    "world",
    "arm",
    "gripper",
    "camera",
    "tactile",
    "cloud_processor",
    "shape_estimator",
    "view_planner",
    "filter",
    "process_model",
    "observation_model",
    "action_sampler",
    "action_selector",
    "controller",
    "touch_probe",
    "touch_estimator",
    "touch_explorer",
    "executor",
    "behaviour",
)


@runtime_checkable
class World(Protocol):
    """The environment and its clock. Simulated worlds advance physics in ``step``; a real
    world's ``step`` does nothing (the scheduler then keeps wall-clock time)."""

    simulated: bool

    def reset(self, seed: int) -> None: ...

    def step(self, dt_s: float) -> None: ...

    @property
    def time_s(self) -> float: ...

    def ground_truth(self) -> dict[str, Any] | None:
        """Object parameters and current link poses when known (evaluation only), else None."""
        ...

    def ground_truth_poses(self) -> FloatArray | None:
        """True link poses [L, 3] = (x, y, theta) when known (recording only), else None."""
        ...

    def object_center_m(self) -> FloatArray | None:
        """Where the object is expected (for aiming cameras): [3], or None when unknown."""
        ...


@runtime_checkable
class Arm(Protocol):
    """A Cartesian arm commanded by velocity streaming, (x, y, z, yaw)."""

    max_speed_mps: float

    def state(self) -> ArmState: ...

    def command_velocity(self, twist: FloatArray) -> None:
        """Stream twist [4] = (vx, vy, vz m/s, wz rad/s) for one control period. Speeds above
        the cap are clamped; motion that would leave the workspace is refused."""
        ...

    def stop(self) -> None:
        """Stop all motion now. Safe to call at any time, repeatedly, also when disconnected."""
        ...


@runtime_checkable
class Gripper(Protocol):
    """A two-finger parallel gripper. Commands return at once; poll ``state()``.

    ``close()`` closes the fingers (it shadows ``Component.close``), so the run never calls it
    at its end: a gripper releases its devices in an optional ``release()``, which the run
    calls instead.
    """

    def open(self) -> None: ...

    def close(self) -> None: ...

    def state(self) -> GripperState: ...

    def stop(self) -> None: ...


@runtime_checkable
class Camera(Protocol):
    """A depth camera. Movable cameras (on an arm, or simulated) accept ``move_to``."""

    movable: bool

    def move_to(self, view: Viewpoint) -> None: ...

    def capture(
        self, width: int | None = None, height: int | None = None, window: PixelWindow | None = None
    ) -> RGBD:
        """One frame, optionally cropped to ``window`` (a region of interest of the full
        image, its intrinsics shifted to match), then resampled to ``width x height``."""
        ...


@runtime_checkable
class Tactile(Protocol):
    """Tactile pads giving the 2D fingertip force per pad."""

    def read(self) -> TactileReading: ...

    def bias(self) -> None:
        """Zero the pads (call with nothing in contact)."""
        ...


@runtime_checkable
class ViewPlanner(Protocol):
    """Chooses where the camera looks next."""

    def next_view(
        self, cloud: PointCloud | None, shape: ShapeEstimate | None, views_taken: int
    ) -> Viewpoint | None:
        """The next viewpoint, or None when enough has been seen.

        cloud: the segmented object so far (None before a look's first view). When a later
        look's first view shows no object, ``look`` asks again for view 0 with the object
        cloud of the last look, to aim where the object was last seen.
        """
        ...


@runtime_checkable
class CloudProcessor(Protocol):
    """Registers views onto each other and segments the object from a world-frame cloud."""

    def register(self, view: PointCloud, previous: PointCloud | None) -> PointCloud:
        """``view`` aligned onto the merged ``previous`` views (unchanged when it cannot be)."""
        ...

    def segment(self, cloud: PointCloud) -> PointCloud:
        """The object's points only (table and clutter removed)."""
        ...


@runtime_checkable
class ShapeEstimator(Protocol):
    """Fits the object's shape (one part per link) to a segmented or raw cloud."""

    def fit(self, cloud: PointCloud) -> ShapeEstimate: ...


@dataclass(frozen=True)
class Scene:
    """What the robot knows before it acts: the observed cloud (world frame, table included),
    the shape estimate when there is one, and the current belief when there is one.
    blocked_xy_m [K, 2]: the action points (world, m) of actions whose way down to the object
    was blocked since the last interaction (see ``Executor``); choosers keep away from them."""

    cloud: PointCloud
    shape: ShapeEstimate | None = None
    belief: GaussianBelief | None = None
    blocked_xy_m: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


@runtime_checkable
class ActionSampler(Protocol):
    """Proposes candidate pushes and pulls."""

    def sample(self, scene: Scene, rng: np.random.Generator) -> list[Action]: ...


@runtime_checkable
class ActionSelector(Protocol):
    """Picks one action among candidates."""

    def select(
        self, candidates: Sequence[Action], scene: Scene, rng: np.random.Generator
    ) -> Action: ...


@dataclass
class StepObservation:
    """One control step's observation during an interaction.

    tactile: fingertip forces; arm: TCP state; depth: the depth frame (an [h, w] image with
    its intrinsics and camera pose) or None; ground_truth_poses: link poses [L, 3] = (x, y,
    theta) when the world knows them (never read by estimators).
    """

    time_s: float
    tactile: TactileReading
    arm: ArmState
    depth: RGBD | None = None
    ground_truth_poses: FloatArray | None = None


@dataclass
class Episode:
    """One executed interaction: the action and its observation stream at the control rate."""

    index: int
    action: Action
    steps: list[StepObservation] = field(default_factory=list)
    outcome: str = "ok"


@runtime_checkable
class Executor(Protocol):
    """Turns a push or pull into arm and gripper commands, one control period per call.

    Optionally an executor has ``blocked_at_m``: where (x, y, z) it found its way to the
    action blocked and backed off before the interaction, or None. ``execute_action`` then
    records no episode and the next ``choose_action`` avoids the spot."""

    def start(self, action: Action) -> None: ...

    def step(self, dt_s: float) -> tuple[str, bool]:
        """Command one control period. Returns (phase name, whether the interaction proper
        (the part the filter observes) is in progress). Phase ``"done"`` ends the action."""
        ...

    def abort(self) -> None: ...


@runtime_checkable
class Filter(Protocol):
    """Belief over object parameters and link poses."""

    def initialise(self, scene: Scene) -> GaussianBelief: ...

    def update(self, episode: Episode) -> GaussianBelief: ...


@runtime_checkable
class ProcessModel(Protocol):
    """Predicts the next time-varying state of C sigma points (torch, float64).

    ``predict(states [..., C, n], inputs: ProcessInput, dt_s) -> Prediction`` with
    ``Prediction.pose [..., C, 6 L]``, ``force_n [..., C, 2]`` and ``process_var``; see
    ``vistac.plugins.filters.state`` for the state layout. ``n_links`` is the number of links
    the model supports, the tuple of numbers it supports, or None for any number (the GNN).
    """

    n_links: int | tuple[int, ...] | None

    def predict(self, states: Any, inputs: Any, dt_s: float) -> Any: ...


@runtime_checkable
class ObservationModel(Protocol):
    """Expected observation per sigma point and the observation noise.

    ``expected(states [..., C, n], prediction) -> [..., C, k]`` and
    ``noise_var(observation [..., k]) -> [..., k]`` (diagonal R), torch float64.
    """

    def expected(self, states: Any, prediction: Any) -> Any: ...

    def noise_var(self, observation: Any) -> Any: ...


@runtime_checkable
class Controller(Protocol):
    """Plans an action towards a goal from the current belief."""

    def plan(self, scene: Scene, goal: FloatArray, rng: np.random.Generator) -> Action: ...


@runtime_checkable
class TouchProbe(Protocol):
    """Moves from ``start_m`` [3] towards ``target_m`` [3] until contact.

    Returns (contact point [3], surface normal [3]) or None for a miss."""

    def probe(
        self, start_m: FloatArray, target_m: FloatArray
    ) -> tuple[FloatArray, FloatArray] | None: ...


@runtime_checkable
class TouchEstimator(Protocol):
    """Belief over (class, pose) or shape from touches."""

    def update(
        self,
        start_m: FloatArray,
        target_m: FloatArray,
        contact: tuple[FloatArray, FloatArray] | None,
    ) -> dict[str, Any]: ...


@runtime_checkable
class TouchExplorer(Protocol):
    """Chooses the next touch: (start [3], target [3]), or None to stop."""

    def next_touch(
        self, estimate: dict[str, Any], rng: np.random.Generator
    ) -> tuple[FloatArray, FloatArray] | None: ...


PROTOCOLS: dict[str, type] = {
    "world": World,
    "arm": Arm,
    "gripper": Gripper,
    "camera": Camera,
    "tactile": Tactile,
    "view_planner": ViewPlanner,
    "cloud_processor": CloudProcessor,
    "shape_estimator": ShapeEstimator,
    "action_sampler": ActionSampler,
    "action_selector": ActionSelector,
    "executor": Executor,
    "filter": Filter,
    "process_model": ProcessModel,
    "observation_model": ObservationModel,
    "controller": Controller,
    "touch_probe": TouchProbe,
    "touch_estimator": TouchEstimator,
    "touch_explorer": TouchExplorer,
}
