"""Dual filter speed: one step (predict + update) with C = 100 sigma points.

Target: >= 100 Hz for a two-link object (L = 2) with the GNN process model (hidden 64,
fresh weights) and the 4098-dim observation (a 64x64 render of a 2000-point cloud + force),
torch on one thread. Peer in the same run: filterpy's UnscentedKalmanFilter on the pose-only
part of the same problem (6 L = 12-dim state, the same render as its observation function).
The same step with the analytical model of the chain (``filters.analytical``, a Newton solve
per step) must keep up with the skills' 15 Hz control rate; its peer is the GNN's step. The
pusher touches the object, so the analytical model solves a push in contact.
"""

from __future__ import annotations

import math
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from common import Row, median_time_s
from vistac.plugins.filters.chain import NEWTON_STEPS, NEWTON_TOLERANCE
from vistac.plugins.filters.dual import Belief, DualFilter
from vistac.plugins.filters.observation import (
    DepthProjector,
    ObsNoiseNet,
    ProjectionObservationModel,
    observation_vector,
)
from vistac.plugins.filters.state import DTYPE, ProcessInput, StateLayout
from vistac.testing import build_components
from vistac.types import CameraIntrinsics

TARGET_HZ = 100.0
DT_S = 1.0 / 15.0
LINKS = 2
TCP = [-0.101, 0.45, 0.0, 0.02, 0.0, 0.0]
"""The pusher (x, y, yaw, their rates): at link 0's left face, pushing along +x, so that the
analytical model solves a push in contact (out of contact its motion is discarded)."""


def _camera() -> np.ndarray:
    """Optical frame 0.5 m from the object, looking down at 60 degrees."""
    tilt = math.radians(60.0)
    forward = np.array([0.0, math.cos(tilt), -math.sin(tilt)])
    right = np.array([1.0, 0.0, 0.0])
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([right, down, forward])
    pose[:3, 3] = np.array([0.0, 0.45, 0.0]) - 0.5 * forward
    return pose


def _problem() -> tuple[StateLayout, DepthProjector, Belief, ProcessInput, torch.Tensor]:
    rng = np.random.default_rng(0)
    layout = StateLayout(LINKS)
    initial = np.array([[-0.05, 0.45, 0.0], [0.05, 0.45, 0.0]])
    points = np.column_stack([
        rng.uniform(-0.1, 0.1, 2000), 0.45 + rng.uniform(-0.04, 0.04, 2000),
        rng.uniform(0.0, 0.05, 2000),
    ])  # fmt: skip
    links = (points[:, 0] > 0).astype(np.int64)
    intrinsics = CameraIntrinsics.from_fov(320, 240, math.radians(58.0))
    projector = DepthProjector(points, links, initial, intrinsics, _camera(), splat_px=1)
    mean = torch.zeros(layout.size, dtype=DTYPE)
    mean[0:3] = torch.as_tensor(initial[0])
    mean[6:9] = torch.as_tensor(initial[1])
    mean[12:20] = torch.tensor([0.5, 0.3, 0.0, 0.0] * 2, dtype=DTYPE)
    mean[20] = 0.2
    std = torch.full((layout.size,), 0.005, dtype=DTYPE)
    std[12:] = 0.05
    belief = Belief(mean, torch.diag(std**2))
    inputs = ProcessInput(
        tcp=torch.tensor(TCP, dtype=DTYPE),
        pd_rad=torch.tensor(0.0, dtype=DTYPE),
        is_pull=torch.tensor(0.0, dtype=DTYPE),
        link=torch.tensor(0),
        link_size_m=torch.tensor([[0.05, 0.04]] * 2, dtype=DTYPE),
        link_offset=torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]], dtype=DTYPE),
    )
    shifted = torch.as_tensor(initial, dtype=DTYPE) + torch.tensor([0.003, 0.0, 0.0])
    observation = observation_vector(
        projector.render(shifted), torch.tensor([0.5, 0.0], dtype=DTYPE), projector.background_m
    )
    return layout, projector, belief, inputs, observation


GNN = {"plugin": "filters.gnn", "with": {"hidden": 64}}
ANALYTICAL = {"plugin": "filters.analytical"}


def time_dual_step_s(repeats: int, model_spec: dict[str, Any]) -> tuple[float, float]:
    """Median wall and CPU (this thread's) time of one step: the machine may be shared."""
    layout, projector, belief, inputs, observation = _problem()
    with tempfile.TemporaryDirectory() as tmp:
        model = build_components({"m": model_spec}, Path(tmp)).component("m")
    observation_model = ProjectionObservationModel(layout, projector, ObsNoiseNet())
    dual = DualFilter(layout, model, observation_model, 100, push_load_only=True)  # as skills
    generator = torch.Generator().manual_seed(0)
    cpu_s: list[float] = []

    def step() -> None:
        start = time.thread_time()
        with torch.no_grad():
            dual.step(belief, inputs, DT_S, observation, generator)
        cpu_s.append(time.thread_time() - start)

    warmup = 30  # the steady state of a push's 75 steps: the heap has settled by then
    wall_s = median_time_s(step, repeats, warmup=warmup)
    return wall_s, statistics.median(cpu_s[warmup:])


def time_filterpy_step_s(repeats: int) -> float:
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    layout, projector, belief, _, observation = _problem()
    n = layout.n_pose

    def fx(x: np.ndarray, dt: float) -> np.ndarray:
        poses = x.reshape(LINKS, 6).copy()
        poses[:, :3] += dt * poses[:, 3:]
        return poses.reshape(-1)

    def hx(x: np.ndarray) -> np.ndarray:
        poses = torch.as_tensor(x.reshape(LINKS, 6)[:, :3], dtype=DTYPE)
        depth = projector.render(poses).reshape(-1).numpy()
        return np.concatenate([depth, np.zeros(2)])

    ukf = UnscentedKalmanFilter(
        n, observation.numel(), DT_S, hx, fx, MerweScaledSigmaPoints(n, 0.5, 2.0, 0.0)
    )
    start_x = belief.mean[:n].numpy().copy()
    start_p = belief.cov[:n, :n].numpy().copy()
    ukf.R = np.eye(observation.numel()) * 0.005**2
    ukf.Q = np.eye(n) * 1e-6
    z = observation.numpy()

    def step() -> None:
        ukf.x, ukf.P = start_x.copy(), start_p.copy()
        ukf.predict()
        ukf.update(z)

    return median_time_s(step, peer_repeats(repeats), warmup=1)


def peer_repeats(repeats: int) -> int:
    """The filterpy UKF's timed steps (each takes seconds): a fifth of ``repeats``, >= 3."""
    return max(3, repeats // 5)


def run(repeats: int) -> list[Row]:
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        dual_s, dual_cpu_s = time_dual_step_s(repeats, GNN)
        chain_repeats = max(3, repeats // 2)
        chain_s, chain_cpu_s = time_dual_step_s(chain_repeats, ANALYTICAL)
        try:
            peer_s: float | None = time_filterpy_step_s(repeats)
        except ImportError:
            peer_s = None
    finally:
        torch.set_num_threads(threads)
    return [
        Row(
            name="dual filter step (C=100, L=2, GNN 64, 4098 obs)",
            value=1.0 / dual_s,
            unit="Hz",
            target=f">= {TARGET_HZ:g} Hz",
            passed=1.0 / dual_s >= TARGET_HZ,
            peer="filterpy UKF, pose only (12 dims)",
            peer_value=None if peer_s is None else 1.0 / peer_s,
            note=f"torch threads = 1; CPU time {1e3 * dual_cpu_s:.1f} ms a step"
            + (f"; peer: median of {peer_repeats(repeats)}" if peer_s is not None
               else "; filterpy missing"),
        ),
        Row(
            name="dual filter step (C=100, L=2, analytical chain, 4098 obs)",
            value=1.0 / chain_s,
            unit="Hz",
            target=f">= {1.0 / DT_S:g} Hz (the control rate)",
            passed=chain_s <= DT_S,
            peer="the same step with the GNN 64",
            peer_value=1.0 / dual_s,
            note=f"torch threads = 1; CPU time {1e3 * chain_cpu_s:.1f} ms a step; minimum-power "
            f"Newton solve, each sigma point until its step is under {NEWTON_TOLERANCE:g} "
            f"(at most {NEWTON_STEPS} iterations); pusher in contact; median of {chain_repeats}",
        ),
    ]


if __name__ == "__main__":
    for row in run(20):
        print(row)
