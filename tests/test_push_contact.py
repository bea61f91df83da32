"""A push moves the object only in contact: the missed-push copies training adds
(``missed_push``) and what the shipped push model learned from them."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from simctx import TestContext
from vistac.objects import link_frames, load_object
from vistac.plugins.filters.data import MISS_MARGIN_M, Trajectory, _path_gap_m, missed_push
from vistac.plugins.filters.models import AnalyticalProcessModel, GNNProcessModel
from vistac.plugins.filters.state import DTYPE, ProcessInput

pytestmark = pytest.mark.usefixtures("single_thread")

ROOT = Path(__file__).resolve().parents[1]
STEPS, DT_S, SPEED_MPS = 45, 1 / 15, 0.02


def _push(start_x_m: float, speed_mps: float = SPEED_MPS) -> Trajectory:
    """rect1 at its start pose, pushed along +x from x = start_x_m (relative to its centre) at
    speed_mps; the object moves along with the TCP once the TCP is past the start."""
    spec = load_object(ROOT / "skills/objects/rect1.yaml")
    start = link_frames(spec)[0]
    time_s = np.arange(STEPS) * DT_S
    tcp = np.zeros((STEPS, 6))
    tcp[:, 0] = start[0] + start_x_m + speed_mps * time_s
    tcp[:, 1], tcp[:, 3] = start[1], speed_mps
    poses = np.tile(start, (STEPS, 1, 1))
    poses[:, 0, 0] += 0.5 * speed_mps * time_s
    twists = np.zeros((STEPS, 1, 3))
    twists[:, 0, 0] = 0.5 * speed_mps
    return Trajectory(
        source="synthetic", spec=spec, kind="push", pd_rad=0.0, link=0, dt_s=DT_S,
        poses=poses, twists=twists, tcp=tcp, force_n=np.tile([2.0, 0.0], (STEPS, 1)),
        depth_m=np.zeros((STEPS, 4, 4)), camera_pose=np.tile(np.eye(4), (STEPS, 1, 1)),
        intrinsics=None, parameters={"m_0": 0.8, "f_0": 0.3, "com_x_0": 0.0, "com_y_0": 0.0},
    )  # fmt: skip


@pytest.mark.parametrize("lateral", [False, True])
def test_a_missed_push_passes_the_object_by_and_leaves_it_at_rest(lateral: bool) -> None:
    push = _push(start_x_m=-0.08)
    missed = missed_push(push, lateral)
    assert missed is not None
    link, start = push.spec.links[0], push.poses[0, 0]
    assert _path_gap_m(missed.tcp[:, :2], link, start) >= MISS_MARGIN_M
    np.testing.assert_array_equal(missed.poses, np.repeat(push.poses[:1], STEPS, axis=0))
    assert not missed.twists.any() and not missed.force_n.any()
    assert missed.depth_m is None and missed.camera_pose is None
    np.testing.assert_array_equal(missed.tcp[:, 2:], push.tcp[:, 2:])  # same motion
    np.testing.assert_allclose(np.diff(missed.tcp[:, :2], axis=0), np.diff(push.tcp[:, :2], axis=0))
    assert _path_gap_m(push.tcp[:, :2], link, start) < MISS_MARGIN_M  # the original touched


def test_a_push_whose_shifted_path_would_cross_the_object_is_not_used() -> None:
    """A TCP that starts beyond the object and moves away from it: moved back by its own
    length, it would cross the object."""
    assert missed_push(_push(start_x_m=0.07), lateral=False) is None


def _rolled_out(
    start_x_m: float, start_y_m: float, steps: int, com_y_m: float = 0.0, model: Any = None
) -> torch.Tensor:
    """The pose (x, y, theta, vx, vy, omega) [6] to which the shipped push model (or
    ``model``) moves a 80 x 60 mm box at the origin (CoM at (0, com_y_m)) when the TCP
    starts at (start_x_m, start_y_m) and moves along +x at 20 mm/s for ``steps`` steps."""
    if model is None:
        checkpoint = ROOT / "skills/checkpoints/gnn_push.pt"
        model = TestContext(ROOT, 0).add(GNNProcessModel, hidden=32, checkpoint=str(checkpoint))
    state = torch.tensor([[0.0] * 6 + [0.8, 0.3, 0.0, com_y_m]], dtype=DTYPE)
    for step in range(steps):
        tcp_x_m = start_x_m + SPEED_MPS * step * DT_S
        inputs = ProcessInput(
            tcp=torch.tensor([tcp_x_m, start_y_m, 0.0, SPEED_MPS, 0.0, 0.0], dtype=DTYPE),
            pd_rad=torch.tensor(0.0, dtype=DTYPE), is_pull=torch.tensor(0.0, dtype=DTYPE),
            link=torch.tensor(0), link_size_m=torch.tensor([[0.04, 0.03]], dtype=DTYPE),
            link_offset=torch.zeros(1, 3, dtype=DTYPE),
        )  # fmt: skip
        with torch.no_grad():
            state = torch.cat([model.predict(state, inputs, DT_S).pose, state[:, 6:]], -1)
    return state[0, :6]


def _rollout_m(start_x_m: float, start_y_m: float, steps: int) -> float:
    """How far (m) the shipped push model moves the box (see :func:`_rolled_out`)."""
    return float(torch.linalg.vector_norm(_rolled_out(start_x_m, start_y_m, steps)[:2]))


def test_the_shipped_push_model_moves_the_object_only_in_contact() -> None:
    """The TCP starts 2 cm behind the box (the pad, 1 cm ahead of it, 1 cm short): 3 s at
    20 mm/s pushes the box about 4-5 cm in simulation. Pushes that stop short, or pass
    beside it, or start far behind it leave it (nearly) where it is. (Measured when shipped:
    50.1, 0.5, 2.8 and 0.5 mm; before the twist noise of training, 53.0, 0.6, 17.5 and
    0.2 mm; the model trained on the 5 shipped objects gave 45.9, 0.3, 6.7 and 2.0 mm;
    without missed pushes, 43.2, 4.8, 33.5 and 31.0 mm.)"""
    reached = _rollout_m(-0.06, 0.0, STEPS)
    assert reached > 0.03
    assert _rollout_m(-0.10, 0.0, 15) < 0.003  # 1 s, the pad ends 3 cm short
    assert _rollout_m(-0.06, 0.06, STEPS) < 0.4 * reached  # beside: the pad 1.8 cm clear of +y
    assert _rollout_m(-0.15, 0.0, STEPS) < 0.005  # the pad ends 4 cm short


def test_the_shipped_push_model_turns_the_object_about_its_com() -> None:
    """A push along +x through the box's centre turns it one way or the other by its CoM:
    CoM 2 cm to the left (+y), the push line passes right of it and the box turns
    counter-clockwise; CoM to the right, clockwise, as Lynch's quasi-static model says.
    (Measured when shipped: +11.5 and -18.3 deg; the analytical model +12.5 and -12.5 deg.
    The checkpoint trained from the true twist at each rollout start turned the box by -1.9
    and -5.9 deg: it carried the twist on and had not learned what turns the object.)"""
    analytical = TestContext(ROOT, 0).add(AnalyticalProcessModel)
    for model in (None, analytical):
        left = float(_rolled_out(-0.06, 0.0, STEPS, com_y_m=0.02, model=model)[2])
        right = float(_rolled_out(-0.06, 0.0, STEPS, com_y_m=-0.02, model=model)[2])
        assert left > math.radians(2) and right < -math.radians(2)
