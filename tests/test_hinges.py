"""``vistac objects hinges``: which pushes turn a hinged object's hinge in the simulated
world."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from vistac.cli import main
from vistac.objects import link_frames, load_object
from vistac.plugins.actions.executor import CartesianExecutor
from vistac.plugins.filters.hinges import (
    POINTS,
    SPEED_MPS,
    SquarePush,
    hinge_turns,
    hinges_markdown,
    square_push,
)

ROOT = Path(__file__).resolve().parents[1]
HINGED = ROOT / "skills/objects/artic_rect_rect.yaml"  # two 90 mm squares, 0.05 N m


def test_a_square_push_starts_clear_of_its_link_and_moves_square_to_the_chain() -> None:
    """Link 1 of the pair along world x, pushed from its +y side at its middle: the gripper
    starts the executor's standoff and pad offset beyond the 45 mm half width, straight
    above the link's origin, and moves along -y at the push speed, at the finger height."""
    spec = load_object(HINGED)
    push = square_push(spec, link=1, along=0.0, side=1.0)
    x_m, y_m, theta_rad = link_frames(spec)[1]
    executor = CartesianExecutor.Config()
    assert theta_rad == 0.0 and push.pd_rad == pytest.approx(-math.pi / 2)
    clear_m = 0.045 + executor.standoff_m + executor.pusher_offset_m
    np.testing.assert_allclose(push.arm_pose[0], [x_m, y_m + clear_m, executor.finger_height_m,
                                                  -math.pi / 2], atol=1e-9)  # fmt: skip
    speed = np.linalg.norm(np.diff(push.arm_pose[:, :2], axis=0), axis=1) / np.diff(push.time_s)
    np.testing.assert_allclose(speed, SPEED_MPS)
    np.testing.assert_allclose(np.diff(push.arm_pose[:, 0]), 0.0, atol=1e-12)
    at_rest = np.broadcast_to(link_frames(spec), push.object_pose.shape)
    np.testing.assert_allclose(push.object_pose, at_rest)


def test_a_hinge_turns_below_its_friction_and_holds_above_it() -> None:
    """The same 20 pushes turn the hinge at 0.05 N m (most of them, by far more than 3 deg)
    and not at all at 2 N m, where the pair moves as one body (and still moves)."""
    spec = load_object(HINGED)
    slipping, held = hinge_turns(spec), hinge_turns(spec, joint_friction_nm=2.0)
    assert len(slipping) == len(held) == 2 * 2 * len(POINTS)
    assert sum(p.turn_rad > math.radians(3) for p in slipping) >= 10
    assert max(p.turn_rad for p in slipping) > math.radians(15)
    assert max(p.turn_rad for p in held) < math.radians(1)
    assert np.median([p.moved_m for p in held]) > 0.03


def test_the_table_counts_the_turning_pushes_and_names_the_largest() -> None:
    pushes = [SquarePush(0, 0.4, 1.0, math.radians(2), 0.05),
              SquarePush(1, -0.8, -1.0, math.radians(12), 0.07),
              SquarePush(1, 0.0, 1.0, math.radians(4), 0.09)]  # fmt: skip
    lines = hinges_markdown({"pair": (0.25, pushes)}, math.radians(3))
    assert lines[-1] == "| pair | 0.250 | 2 of 3 | 12.0 | link 1 at -0.8, from -y | 7.0 |"


def test_the_command_reports_each_object_and_refuses_what_has_no_hinge(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "hinges.json"
    code = main(["-q", "objects", "hinges", str(HINGED), "--joint-friction", "0.3",
                 "--out", str(out)])  # fmt: skip
    assert code == 0
    assert "| artic_rect_rect | 0.300 |" in capsys.readouterr().out
    report = json.loads(out.read_text(encoding="utf-8"))
    assert report["artic_rect_rect"]["joint_friction_nm"] == 0.3
    assert len(report["artic_rect_rect"]["pushes"]) == 20
    single = str(ROOT / "skills/objects/rect2.yaml")
    assert main(["-q", "objects", "hinges", str(HINGED), single]) == 2
    assert "rect2 (homogeneous): no hinge to turn" in capsys.readouterr().err
    assert main(["-q", "objects", "hinges", str(HINGED), "--out", str(tmp_path)]) == 2
    assert "is a folder; give a file" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["-q", "objects", "hinges", str(HINGED), "--joint-friction", "-0.1"])
    assert exit_info.value.code == 2
    assert "not a finite number of 0 or more" in capsys.readouterr().err
