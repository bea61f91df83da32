"""``vistac eval``: NRMSE, pose-change errors, normalisation ranges, and one short run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from vistac.cli import main
from vistac.objects import generate_configurations, object_from_dict
from vistac.plugins.filters.evaluate import (
    match_links,
    nrmse,
    nrmse_rows,
    parameter_pairs,
    parameter_ranges,
    pose_change_errors,
)

ROOT = Path(__file__).resolve().parents[1]
RANGES = {"m": 1.4, "f": 0.4, "CoM": 0.05, "f_j": 0.5}


def _belief(values: dict[str, float]) -> dict[str, dict[str, float]]:
    return {name: {"mean": value, "std": 0.1} for name, value in values.items()}


def test_nrmse_by_hand_with_radial_com() -> None:
    truth_a = {"m_0": 0.8, "f_0": 0.3, "com_x_0": 0.0, "com_y_0": 0.02}
    truth_b = {"m_0": 0.8, "f_0": 0.4, "com_x_0": 0.0, "com_y_0": -0.01}
    # radial CoM: estimate 0.05 vs truth 0.02 (error 0.03); 0.01 vs 0.01 (error 0, rotated)
    run_a = parameter_pairs(
        _belief({"m_0": 0.9, "f_0": 0.35, "com_x_0": 0.03, "com_y_0": 0.04}), truth_a, {0: 0}
    )
    run_b = parameter_pairs(
        _belief({"m_0": 0.5, "f_0": 0.3, "com_x_0": -0.006, "com_y_0": 0.008}), truth_b, {0: 0}
    )
    assert run_a["CoM_0"] == pytest.approx((0.05, 0.02))
    rows = nrmse_rows([run_a, run_b], RANGES)
    expected = {
        "m_0": math.sqrt((0.1**2 + 0.3**2) / 2) / 1.4,
        "f_0": math.sqrt((0.05**2 + 0.1**2) / 2) / 0.4,
        "CoM_0": math.sqrt((0.03**2 + 0.0**2) / 2) / 0.05,
    }
    for name, value in expected.items():
        assert rows[name] == pytest.approx(value)
    assert rows["overall"] == pytest.approx(sum(expected.values()) / 3)
    assert rows["m_0"] == pytest.approx(0.159719, abs=1e-6)
    assert math.isnan(nrmse([], 1.0))


def test_rows_follow_the_matched_true_link_and_joint() -> None:
    truth = {"m_0": 0.5, "f_0": 0.2, "com_x_0": 0.0, "com_y_0": 0.0,
             "m_1": 1.0, "f_1": 0.4, "com_x_1": 0.01, "com_y_1": 0.0, "f_j_0": 0.1}  # fmt: skip
    belief = _belief({"m_0": 1.1, "f_0": 0.4, "com_x_0": 0.0, "com_y_0": 0.0, "m_1": 0.5,
                      "f_1": 0.2, "com_x_1": 0.0, "com_y_1": 0.0, "f_j_0": 0.2})  # fmt: skip
    links = match_links(np.array([[0.1, 0.0], [0.0, 0.0]]), np.array([[0.0, 0.0], [0.1, 0.0]]))
    assert links == {0: 1, 1: 0}
    pairs = parameter_pairs(belief, truth, links)
    assert pairs["m_1"] == (1.1, 1.0) and pairs["m_0"] == (0.5, 0.5)
    assert pairs["f_j_0"] == (0.2, 0.1)
    rows = nrmse_rows([pairs], RANGES)
    assert rows["f_j_0"] == pytest.approx(0.1 / 0.5)
    assert list(rows) == ["m_0", "m_1", "f_0", "f_1", "CoM_0", "CoM_1", "f_j_0", "overall"]


def test_pose_change_error_by_hand() -> None:
    # The true link turns by 90 deg about its origin and moves 0.1 m along x. The belief's
    # frame starts 0.02 m along x from the link frame and flipped by pi (superquadric frame).
    truth = np.array([[[0.0, 0.0, 0.0]], [[0.1, 0.0, math.pi / 2]]])  # [T=2, L=1, 3]
    exact = np.array([[[0.02, 0.0, math.pi]], [[0.1, 0.02, 1.5 * math.pi]]])
    position, angle = pose_change_errors(exact, truth)
    assert position.shape == angle.shape == (2, 1)
    np.testing.assert_allclose(position, 0.0, atol=1e-12)
    np.testing.assert_allclose(angle, 0.0, atol=1e-12)
    off = exact.copy()
    off[1, 0] = [0.1, 0.05, 1.5 * math.pi + 0.1]
    position, angle = pose_change_errors(off, truth)
    assert position[1, 0] == pytest.approx(0.03)
    assert angle[1, 0] == pytest.approx(0.1)


def test_pose_change_error_wraps_angles() -> None:
    truth = np.array([[[0.0, 0.0, 0.0]], [[0.0, 0.0, 0.08]]])
    belief = np.array([[[0.0, 0.0, 3.1]], [[0.0, 0.0, -3.1]]])  # turned +0.0832 rad
    _, angle = pose_change_errors(belief, truth)
    assert angle[1, 0] == pytest.approx(2 * math.pi - 6.2 - 0.08, abs=1e-9)


def test_parameter_ranges() -> None:
    specs = generate_configurations(0)
    ranges = parameter_ranges(specs)
    assert ranges["m"] == pytest.approx(1.4) and ranges["f"] == pytest.approx(0.4)
    assert ranges["f_j"] == pytest.approx(0.5)
    radial = [math.hypot(*link.com_m) for spec in specs for link in spec.links]
    assert ranges["CoM"] == pytest.approx(max(radial) - min(radial))
    assert 0.0 < ranges["CoM"] < 0.1
    assert parameter_ranges() == ranges  # the default set is the 120 configurations, seed 0
    empirical = parameter_ranges(specs, empirical=True)
    assert all(0 < empirical[k] <= ranges[k] + 1e-12 for k in ("m", "f", "f_j"))
    two = [
        object_from_dict({"name": f"o{i}", "type": "homogeneous", "pose": [0, 0.45, 0],
                          "links": [{"footprint": "rect1", "height_m": 0.05, "mass_kg": 0.5,
                                     "friction": 0.3, "com_m": com}]})
        for i, com in enumerate([(0.01, 0.0), (0.0, 0.03)])
    ]  # fmt: skip
    assert parameter_ranges(two)["CoM"] == pytest.approx(0.02)


FAST = ["--set", "components.views.with.max_views=1",
        "--set", "components.filter.with.sigma_points=16",
        "--set", "components.affordances.with.duration_s=2",
        "--set", "components.camera.with.width=160",
        "--set", "components.camera.with.height=120"]  # fmt: skip


def test_eval_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "eval"
    code = main([
        "-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(out),
        "--objects", str(ROOT / "skills/objects/rect2.yaml"), "--models", "gnn,analytical",
        "--max-interactions", "1", *FAST,
    ])  # fmt: skip
    assert code == 0
    for name in ("tables.md", "tables.json", "eval.json", "nrmse_vs_interactions.png",
                 "belief_rect2_gnn.png", "belief_rect2_analytical.png"):  # fmt: skip
        assert (out / name).stat().st_size > 0, name
    markdown = (out / "tables.md").read_text(encoding="utf-8")
    assert "| gnn | analytical |" in markdown and "gnn_fixed" in markdown
    tables = json.loads((out / "tables.json").read_text(encoding="utf-8"))
    report = json.loads((out / "eval.json").read_text(encoding="utf-8"))
    assert report["interaction"] == "push"
    cell = tables["tables"]["homogeneous"]["push"]
    assert set(cell) == {"gnn", "analytical"}
    ranges = tables["ranges"]
    assert ranges["CoM"] == pytest.approx(parameter_ranges()["CoM"])
    for model in ("gnn", "analytical"):
        summary = json.loads((out / "runs/rect2" / model / "summary.json").read_text())
        belief, truth = summary["belief"], summary["ground_truth"]["parameters"]
        by_hand = {
            "m_0": abs(belief["m_0"]["mean"] - truth["m_0"]) / ranges["m"],
            "f_0": abs(belief["f_0"]["mean"] - truth["f_0"]) / ranges["f"],
            "CoM_0": abs(math.hypot(belief["com_x_0"]["mean"], belief["com_y_0"]["mean"])
                         - math.hypot(truth["com_x_0"], truth["com_y_0"])) / ranges["CoM"],
        }  # fmt: skip
        for name, value in by_hand.items():
            assert math.isfinite(cell[model][name])
            assert cell[model][name] == pytest.approx(value)
        assert cell[model]["overall"] == pytest.approx(sum(by_hand.values()) / 3)
        assert report["nrmse_vs_interactions"][model] == pytest.approx([cell[model]["overall"]])
    tracking = tables["tracking"]["homogeneous"]
    assert {"gnn", "gnn_fixed", "analytical"} <= set(tracking)
    assert all(math.isfinite(v["position_m"]) and v["position_m"] < 0.05 for v in tracking.values())


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--models", "gnn,lstm"], "unknown model(s) 'lstm'"),
        (["--objects", "nowhere/missing.yaml"], "neither a split"),
    ],
    ids=["unknown-model", "missing-object"],
)
def test_eval_bad_input_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    code = main(
        ["-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(tmp_path), *args]
    )
    assert code == 2
    assert message in capsys.readouterr().err
