"""``vistac eval``: NRMSE, pose-change errors, normalisation ranges, and one short run."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from conftest import fake_run
from vistac.cli import main
from vistac.errors import DataError
from vistac.objects import generate_configurations, load_object, object_from_dict
from vistac.plugins.filters.component import Prior
from vistac.plugins.filters.evaluate import (
    VARIANTS,
    EvalOptions,
    RunPlan,
    calibration_table,
    chosen_variants,
    difference_table,
    execute,
    first_poses,
    learned_model_options,
    log_score,
    mass_and_com,
    match_links,
    normalised_errors,
    nrmse,
    nrmse_by_interaction,
    nrmse_rows,
    nrmse_tables,
    parameter_pairs,
    parameter_ranges,
    parse_variants,
    plan_runs,
    planner_override,
    pose_change_errors,
    product_posterior_mean,
    reference_records,
    replay_run,
    run_dir_of,
    tables_markdown,
    tracking_table,
    truth_in_belief_frames,
    whole_object,
    whole_object_markdown,
    whole_object_table,
)

ROOT = Path(__file__).resolve().parents[1]
RANGES = {"m": 1.4, "f": 0.4, "CoM": 0.05, "f_j": 0.5}


pytestmark = pytest.mark.usefixtures("single_thread")


def _belief(values: dict[str, float]) -> dict[str, dict[str, float]]:
    return {name: {"mean": value, "std": 0.1} for name, value in values.items()}


def test_nrmse_by_hand_with_the_com_as_a_point() -> None:
    truth_a = {"m_0": 0.8, "f_0": 0.3, "com_x_0": 0.0, "com_y_0": 0.02}
    truth_b = {"m_0": 0.8, "f_0": 0.4, "com_x_0": 0.0, "com_y_0": -0.01}
    # CoM errors: (0.03, 0.04) - (0, 0.02) is 0.036 m; (0, 0.01) against (0, -0.01), as far
    # from the origin but on the other side, is 0.02 m
    run_a = parameter_pairs(
        _belief({"m_0": 0.9, "f_0": 0.35, "com_x_0": 0.03, "com_y_0": 0.04}), truth_a, {0: 0}
    )
    run_b = parameter_pairs(
        _belief({"m_0": 0.5, "f_0": 0.3, "com_x_0": 0.0, "com_y_0": 0.01}), truth_b, {0: 0}
    )
    assert run_a["CoM_0"] == ((0.03, 0.04), (0.0, 0.02))
    rows = nrmse_rows([run_a, run_b], RANGES)
    expected = {
        "m_0": math.sqrt((0.1**2 + 0.3**2) / 2) / 1.4,
        "f_0": math.sqrt((0.05**2 + 0.1**2) / 2) / 0.4,
        "CoM_0": math.sqrt((0.03**2 + 0.02**2 + 0.02**2) / 2) / 0.05,
    }
    for name, value in expected.items():
        assert rows[name] == pytest.approx(value)
    assert rows["overall"] == pytest.approx(sum(expected.values()) / 3)
    assert rows["m_0"] == pytest.approx(0.159719, abs=1e-6)
    assert math.isnan(nrmse([], 1.0))


def test_the_true_com_is_scored_in_the_fitted_frame() -> None:
    # True link 1 at (0.1, 0.2) turned by 90 deg, CoM 0.02 m along its x: the CoM lies at
    # (0.1, 0.22). The fitted frame of belief link 0 sits 0.01 m along +y from the link's
    # origin and is turned by 270 deg (a symmetric footprint's superquadric, flipped): there
    # the CoM is 0.01 m along its -x.
    truth = {"m_1": 1.0, "f_1": 0.4, "com_x_1": 0.02, "com_y_1": 0.0, "f_j_0": 0.2}
    fitted = np.array([[0.1, 0.21, 1.5 * math.pi]])
    poses = (fitted, np.array([[0.0, 0.0, 0.0], [0.1, 0.2, 0.5 * math.pi]]))
    moved = truth_in_belief_frames(truth, {0: 1}, poses)
    assert moved["com_x_1"] == pytest.approx(-0.01) and moved["com_y_1"] == pytest.approx(0.0)
    assert {k: v for k, v in moved.items() if not k.startswith("com_")} == {
        "m_1": 1.0, "f_1": 0.4, "f_j_0": 0.2}  # fmt: skip
    belief = _belief({"m_0": 1.0, "f_0": 0.4, "com_x_0": -0.01, "com_y_0": 0.0})
    assert nrmse_rows([parameter_pairs(belief, moved, {0: 1})], RANGES)["CoM_1"] == pytest.approx(
        0.0, abs=1e-12
    )
    com_entries = normalised_errors(belief, moved, {0: 1})[2:]
    assert [name for name, _, _ in com_entries] == ["com_x_0", "com_y_0"]
    assert [z for _, z, _ in com_entries] == pytest.approx([0.0, 0.0], abs=1e-9)
    # without the belief's frames the CoM cannot be scored
    unknown = truth_in_belief_frames(truth, {0: 1}, None)
    assert "com_x_1" not in unknown and "CoM_1" not in parameter_pairs(belief, unknown, {0: 1})


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


def test_total_mass_and_combined_com_by_hand() -> None:
    """Link 0 at the origin (1 kg, CoM 0.1 m along its x), link 1 at (1, 0) turned by 90 deg
    (3 kg, CoM 0.1 m along its x, so at (1, 0.1) in the world): 4 kg, CoM at
    (1 * (0.1, 0) + 3 * (1, 0.1)) / 4."""
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, math.pi / 2]])
    params = {"m_0": 1.0, "com_x_0": 0.1, "com_y_0": 0.0,
              "m_1": 3.0, "com_x_1": 0.1, "com_y_1": 0.0}  # fmt: skip
    assert mass_and_com(params, poses) == pytest.approx((4.0, 0.775, 0.075))
    massless = mass_and_com(params | {"m_0": -1.0, "m_1": 1.0}, poses)
    assert massless[0] == 0.0 and math.isnan(massless[1]) and math.isnan(massless[2])
    # Moving mass from one link to the other moves the combined CoM, not the total mass.
    moved = mass_and_com(params | {"m_0": 3.0, "m_1": 1.0}, poses)
    assert moved == pytest.approx((4.0, 0.325, 0.025))


def test_whole_object_scores_every_link_in_its_own_frames() -> None:
    """The belief's links in their fitted frames, the truth's in the true link frames; a
    surplus belief link counts in the total; a single-link object has no whole-object score."""
    truth = {"m_0": 1.0, "f_0": 0.3, "com_x_0": 0.0, "com_y_0": 0.0,
             "m_1": 1.0, "f_1": 0.3, "com_x_1": 0.0, "com_y_1": 0.0}  # fmt: skip
    belief = _belief({"m_0": 1.5, "com_x_0": 0.02, "com_y_0": 0.0, "m_1": 0.5, "com_x_1": 0.0,
                      "com_y_1": 0.0, "m_2": 0.1, "com_x_2": 0.0, "com_y_2": 0.0})  # fmt: skip
    prior = _belief({f"{key}_{i}": value for i in range(3) for key, value in
                     (("m", 0.9), ("com_x", 0.0), ("com_y", 0.0))})  # fmt: skip
    true_poses = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]])
    fitted = np.array([[0.0, 0.0, math.pi], [0.2, 0.0, 0.0], [0.1, 0.5, 0.0]])
    summary = {"belief": belief, "prior": prior, "ground_truth": {"parameters": truth}}
    scores = whole_object(summary, (fitted, true_poses))
    assert scores is not None
    assert scores["truth"] == pytest.approx((2.0, 0.1, 0.0))
    # link 0's fitted frame is turned by pi: its CoM 0.02 m along x lies at world x -0.02
    centre = (1.5 * -0.02 + 0.5 * 0.2 + 0.1 * 0.1) / 2.1
    assert scores["estimate"] == pytest.approx((2.1, centre, 0.1 * 0.5 / 2.1))
    assert scores["prior"] == pytest.approx((2.7, 0.1, 0.5 / 3))
    assert whole_object(summary | {"prior": None}, (fitted, true_poses))["prior"] is None
    two_link_prior = {name: entry for name, entry in prior.items() if not name.endswith("_2")}
    assert whole_object(summary | {"prior": two_link_prior}, (fitted, true_poses))["prior"] is None
    single = {"belief": _belief({"m_0": 1.0, "com_x_0": 0.0, "com_y_0": 0.0}),
              "ground_truth": {"parameters": truth}}  # fmt: skip
    assert whole_object(single, (fitted[:1], true_poses[:1])) is None
    assert whole_object(summary, None) is None


def test_whole_object_table_against_the_prior() -> None:
    """RMSE over the multi-link runs per type and column, the prior's from the references;
    single-link runs are left out."""
    records = []
    for name, mass_error, com_error in (("a", 0.1, (0.003, 0.004)), ("b", 0.3, (0.0, 0.0))):
        record = _record("A-GNN", 1.0, 0.001) | {"object": name, "type": "heterogeneous"}
        record["whole_object"] = {"truth": (2.0, 0.1, 0.2),
                                  "estimate": (2.0 + mass_error, 0.1 + com_error[0],
                                               0.2 + com_error[1]),
                                  "prior": (1.8, 0.1, 0.21)}  # fmt: skip
        records.append(record)
    records.append(_record("A-GNN", 1.0, 0.001) | {"whole_object": None})  # one link
    scored = [*records, *reference_records(records, Prior())]
    table = whole_object_table(scored, ["A-GNN", "Prior"])
    assert set(table) == {"heterogeneous", "all"}
    cell = table["heterogeneous"]["push"]
    assert cell["A-GNN"] == pytest.approx(
        {"mass_kg": math.sqrt((0.1**2 + 0.3**2) / 2), "com_m": math.sqrt(0.005**2 / 2),
         "runs": 2.0}
    )  # fmt: skip
    assert cell["Prior"] == pytest.approx({"mass_kg": 0.2, "com_m": 0.01, "runs": 2.0})
    assert table["all"] == table["heterogeneous"]
    markdown = "\n".join(whole_object_markdown(table))
    assert "| heterogeneous | push | Prior | 0.200 | 10.000 | 2 |" in markdown
    assert whole_object_markdown({}) == []


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


def test_the_default_prior_spans_the_generated_object_set() -> None:
    """The filter's default prior has the mean and spread of the 120 generated objects' links
    (within 15%): a narrower CoM prior (it was 1 cm against the set's 2.8 cm) kept the CoM
    estimates near the centre and the uncertainty dishonest."""
    links = [link for spec in generate_configurations(0) for link in spec.links]
    values = {
        "mass_kg": [link.mass_kg for link in links],
        "friction": [link.friction for link in links],
        "com_m": [c for link in links for c in link.com_m],
    }
    prior = Prior()
    for field, samples in values.items():
        mean, std = getattr(prior, field)
        assert mean == pytest.approx(np.mean(samples), abs=0.15 * std), field
        assert std == pytest.approx(np.std(samples), rel=0.15), field


FAST = ["--set", "components.views.with.max_views=1",
        "--set", "components.filter.with.sigma_points=16",
        "--set", "components.affordances.with.duration_s=2",
        "--set", "components.camera.with.width=160",
        "--set", "components.camera.with.height=120"]  # fmt: skip


def _com_error_m(run_dir: Path, summary: dict[str, Any]) -> float:
    """Distance of the final CoM estimate of belief link 0 from the true CoM, both in the
    fitted frame as it lay at the first filter step (a single-link object)."""
    first = summary["filter_steps"][0]
    x, y, theta = (first[f"{key}_0"]["mean"] for key in ("x", "y", "theta"))
    with np.load(run_dir / "episodes" / f"{first['episode']:04d}" / "data.npz") as data:
        link_x, link_y, link_theta = data["object_pose"][0, 0]
    truth = summary["ground_truth"]["parameters"]
    com_x, com_y = truth["com_x_0"], truth["com_y_0"]
    world_x = link_x + math.cos(link_theta) * com_x - math.sin(link_theta) * com_y
    world_y = link_y + math.sin(link_theta) * com_x + math.cos(link_theta) * com_y
    dx, dy = world_x - x, world_y - y
    c, s = math.cos(theta), math.sin(theta)
    local = (c * dx + s * dy, -s * dx + c * dy)
    belief = summary["belief"]
    return math.dist((belief["com_x_0"]["mean"], belief["com_y_0"]["mean"]), local)


def test_eval_end_to_end(tmp_path: Path) -> None:
    out = tmp_path / "eval"
    code = main([
        "-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(out),
        "--objects", str(ROOT / "skills/objects/rect2.yaml"),
        "--variants", "a-gnn,u-gnn,a-analytical,gnn-fixed", "--max-interactions", "1", *FAST,
    ])  # fmt: skip
    assert code == 0
    for name in ("tables.md", "tables.json", "eval.json", "nrmse_vs_interactions.png",
                 "belief_rect2_a-gnn.png", "belief_rect2_a-analytical.png"):  # fmt: skip
        assert (out / name).stat().st_size > 0, name
    markdown = (out / "tables.md").read_text(encoding="utf-8")
    assert "| parameter | A-GNN | U-GNN | A-Analytical |" in markdown
    assert "| homogeneous | GNN-fixed |" in markdown
    tables = json.loads((out / "tables.json").read_text(encoding="utf-8"))
    report = json.loads((out / "eval.json").read_text(encoding="utf-8"))
    assert report["interaction"] == "push"
    assert report["variants"]["U-GNN"] == {
        "model": "gnn", "selector": "uniform", "estimate_parameters": True
    }  # fmt: skip
    cell = tables["tables"]["homogeneous"]["push"]
    assert list(cell) == ["A-GNN", "U-GNN", "A-Analytical", "Prior", "m·f known", "load known"]
    assert tables["differences"] == report["differences"] == {}  # one object: nothing to resample
    assert tables["whole_object"] == {}  # one link: nothing to add up
    assert all(run["joint_bends_rad"] == [] for run in report["runs"])  # and no joint
    first = json.loads((out / "runs/rect2/a-gnn/summary.json").read_text())
    truth, started = first["ground_truth"], first["prior"]  # the belief the run started from
    # The prior's CoM std with the skill's com_discrepancy_m [0.010, 0.011] added.
    kappa1 = first["filter_start"]["links"][0]["superquadric"]["taper"][0]
    com_std_m = math.hypot(0.028, 0.010 + 0.011 * abs(kappa1))
    assert (started["m_0"]["mean"], started["com_x_0"]["std"]) == pytest.approx((0.9, com_std_m))
    m_0 = truth["parameters"]["m_0"]  # the references are scored on the same object
    assert cell["Prior"]["m_0"] == pytest.approx(abs(0.9 - m_0) / 1.4)
    assert cell["m·f known"]["CoM_0"] == 0.0
    assert cell["load known"] == cell["m·f known"]  # a single link: its load centre is its CoM
    ranges = tables["ranges"]
    assert ranges["CoM"] == pytest.approx(parameter_ranges()["CoM"])
    for key, label in (("a-gnn", "A-GNN"), ("a-analytical", "A-Analytical")):
        run_dir = out / "runs/rect2" / key
        summary = json.loads((run_dir / "summary.json").read_text())
        planner = json.loads((run_dir / "run.json").read_text())["config"]["components"]["planner"]
        assert planner["plugin"] == "actions.info_gain"
        belief, truth = summary["belief"], summary["ground_truth"]["parameters"]
        by_hand = {
            "m_0": abs(belief["m_0"]["mean"] - truth["m_0"]) / ranges["m"],
            "f_0": abs(belief["f_0"]["mean"] - truth["f_0"]) / ranges["f"],
            "CoM_0": _com_error_m(run_dir, summary) / ranges["CoM"],
        }  # fmt: skip
        for name, value in by_hand.items():
            assert math.isfinite(cell[label][name])
            assert cell[label][name] == pytest.approx(value)
        assert cell[label]["overall"] == pytest.approx(sum(by_hand.values()) / 3)
        assert report["nrmse_vs_interactions"][label] == pytest.approx([cell[label]["overall"]])
    tracking = tables["tracking"]["homogeneous"]
    assert list(tracking) == ["A-GNN", "U-GNN", "A-Analytical", "GNN-fixed"]
    assert all(math.isfinite(v["position_m"]) and v["position_m"] < 0.05 for v in tracking.values())
    stamp = (out / "runs/rect2/u-gnn/eval_args.json").stat().st_mtime_ns
    code = main([
        "-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(out),
        "--objects", str(ROOT / "skills/objects/rect2.yaml"),
        "--variants", "u-gnn", "--max-interactions", "1", *FAST,
    ])  # fmt: skip
    assert code == 0  # the finished run is reused, not run again
    assert (out / "runs/rect2/u-gnn/eval_args.json").stat().st_mtime_ns == stamp
    report = json.loads((out / "eval.json").read_text(encoding="utf-8"))
    assert list(report["variants"]) == ["U-GNN"]


def test_eval_scores_a_welded_pair_as_a_whole(tmp_path: Path) -> None:
    """A two-link run gets the whole-object table: the prior's total mass error is that of two
    links at the skill's prior mean 0.9 kg; the estimate's combined CoM is finite."""
    out = tmp_path / "eval"
    pair = ROOT / "skills/objects/hetero_rect_tri.yaml"
    code = main(["-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(out),
                 "--objects", str(pair), "--variants", "a-gnn", "--max-interactions", "1",
                 *FAST])  # fmt: skip
    assert code == 0
    tables = json.loads((out / "tables.json").read_text(encoding="utf-8"))
    cell = tables["whole_object"]["heterogeneous"]["push"]
    true_mass = sum(link.mass_kg for link in load_object(pair).links)
    assert cell["Prior"]["mass_kg"] == pytest.approx(abs(2 * 0.9 - true_mass))
    assert math.isfinite(cell["A-GNN"]["com_m"]) and cell["A-GNN"]["runs"] == 1.0
    assert "| heterogeneous | push | A-GNN |" in (out / "tables.md").read_text(encoding="utf-8")
    (record,) = json.loads((out / "eval.json").read_text(encoding="utf-8"))["runs"]
    (bend_rad,) = record["joint_bends_rad"]  # welded: the links never turn apart
    assert 0 <= bend_rad < 1e-3


def test_eval_exits_1_when_a_run_fails(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A corrupted checkpoint fails every run: the eval says which and exits 1, not 0."""
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    (folder / "gnn_push.pt").write_bytes(b"not a state dict")
    sidecar = ROOT / "skills/checkpoints/gnn_push.pt.json"
    (folder / "gnn_push.pt.json").write_text(sidecar.read_text(encoding="utf-8"))
    code = main([
        "-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(tmp_path / "eval"),
        "--objects", str(ROOT / "skills/objects/rect2.yaml"), "--variants", "u-gnn",
        "--checkpoints", str(folder), *FAST,
    ])  # fmt: skip
    assert code == 1
    assert "failed: U-GNN on rect2" in capsys.readouterr().out


def test_eval_names_a_bad_prior(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    skill = tmp_path / "explore.yaml"
    text = (ROOT / "skills/explore_push.yaml").read_text(encoding="utf-8")
    noise = "noise_checkpoint: checkpoints/obs_noise_push.pt,"
    bad = text.replace(noise, "prior: {mass_kg: [0.9]},")
    assert bad != text
    skill.write_text(bad)
    code = main(["-q", "eval", str(skill), "--out", str(tmp_path / "eval"),
                 "--objects", str(ROOT / "skills/objects/rect2.yaml")])  # fmt: skip
    assert code == 2
    assert "prior is invalid (each family is [mean, std]" in capsys.readouterr().err
    assert not (tmp_path / "eval").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--models", "gnn,lstm"], "--models: unknown model(s) 'lstm'"),
        (["--objects", "nowhere/missing.yaml"], "neither a split"),
        (["--variants", "a-gnn,b-gnn"], "--variants: unknown variant(s) 'b-gnn'; choose from "
         "a-gnn, u-gnn, r-gnn, a-ff, a-analytical, gnn-fixed, a-physics"),
        (["--variants", "a-physics"], "a-physics simulates every sigma point and only replays "
         "another variant's interactions: add --paired and a variant before it"),
        (["--variants", "a-ff", "--models", "gnn"], "no variant left to evaluate"),
        (["--variants", ","], "--variants: unknown variant(s) (none)"),
        (["--max-objects", "0"], "--max-objects: 0 is not a count; give 1 or more"),
        (["--max-objects", "-1"], "--max-objects: -1 is not a count"),
        (["--max-interactions", "0"], "--max-interactions: 0 is not a count"),
        (["--max-interactions", "-1"], "--max-interactions: -1 is not a count"),
        (["--trials", "3", "--explorers", "dhd"], "is a parameter-estimation skill; its "
         "evaluation does not use --trials (only for touch and goal-push skills), --explorers "
         "(only for touch skills); leave them out"),
    ],
    ids=["unknown-model", "missing-object", "unknown-variant", "physics-unpaired",
         "no-variant-left", "empty", "no-objects", "objects-negative", "no-interactions",
         "interactions-negative", "touch-options"],
)  # fmt: skip
def test_eval_bad_input_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    code = main(
        ["-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(tmp_path), *args]
    )
    assert code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize(
    ("text", "message"),
    [("tree: [look\n", "malformed YAML: line 2"), ("- look\n", "not a skill (a YAML mapping)")],
)
def test_eval_of_a_skill_that_is_no_mapping_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, message: str
) -> None:
    skill = tmp_path / "skill.yaml"
    skill.write_text(text)
    assert main(["-q", "eval", str(skill), "--out", str(tmp_path / "o")]) == 2
    assert f"{skill}: {message}" in capsys.readouterr().err


def test_eval_out_naming_a_file_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "afile"
    out.write_text("not a folder")
    for where in (out, out / "eval"):
        code = main(["-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(where),
                     "--objects", str(ROOT / "skills/objects/rect2.yaml")])  # fmt: skip
        assert code == 2
        assert f"--out: {out} is a file; give a folder" in capsys.readouterr().err
    assert out.read_text() == "not a folder"


def test_ctrl_c_stops_the_whole_evaluation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The Scheduler turns Ctrl-C into its run's exit 130: eval starts no further run, exits
    130, and stamps no run as finished (before, every run was started and eval exited 1)."""
    from vistac.scheduler import Scheduler

    started: list[Path] = []

    def interrupted(self: Scheduler, tree: object) -> str:
        started.append(self.recorder.out_dir)
        raise KeyboardInterrupt

    monkeypatch.setattr(Scheduler, "_tick_until_done", interrupted)
    out = tmp_path / "eval"
    code = main([
        "-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(out),
        "--objects", str(ROOT / "skills/objects/rect2.yaml"),
        str(ROOT / "skills/objects/rect1.yaml"), "--variants", "a-analytical,r-gnn", *FAST,
    ])  # fmt: skip
    assert code == 130
    assert "interrupted" in capsys.readouterr().err
    assert len(started) == 1
    assert not list(out.rglob("eval_args.json")) and not (out / "eval.json").exists()


def test_a_failed_rerun_is_not_reused_as_the_finished_run_before_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run that finished with seed 0, rerun with seed 1 and failed, then asked for with
    seed 0 again: it runs again (before, the old stamp passed the failed run for it)."""
    rect2 = ROOT / "skills/objects/rect2.yaml"
    plan = RunPlan(rect2, load_object(rect2), VARIANTS[0], overrides=["a=1"])
    options = [EvalOptions(skill=ROOT / "skills/explore_push.yaml", out=tmp_path, seed=seed)
               for seed in (0, 1)]  # fmt: skip
    calls = fake_run(monkeypatch, 0)
    assert execute(plan, options[0])["status"] == "ok"
    fake_run(monkeypatch, 1)
    assert execute(plan, options[1])["status"] == "failed"
    assert not (run_dir_of(tmp_path, plan) / "eval_args.json").exists()
    calls = fake_run(monkeypatch, 0)
    assert execute(plan, options[0])["status"] == "ok" and len(calls) == 1
    fake_run(monkeypatch, 130)
    with pytest.raises(KeyboardInterrupt):
        execute(plan, options[1])
    assert not (run_dir_of(tmp_path, plan) / "eval_args.json").exists()


def test_eval_checks_each_variants_settings_before_running(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A process-model option with a bad value fails at once, naming the variant and the
    option, and leaves no output folder (before, every run exited 2 one after the other)."""
    out = tmp_path / "eval"
    code = main([
        "-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(out),
        "--objects", str(ROOT / "skills/objects/rect2.yaml"), "--variants", "a-analytical",
        "--set", "components.model.with.contact_normal=sideways",
    ])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert "A-Analytical" in err
    assert "components.model.with.contact_normal: Input should be 'push' or 'box'" in err
    assert not out.exists()


# ---------------------------------------------------------------------------------------------
# Variants: model x action selector


def _checkpoints(folder: Path) -> Path:
    """Fake checkpoint files (plan_runs only checks that they exist and reads the sidecars)."""
    folder.mkdir()
    for name, architecture in (("gnn_push.pt", {"hidden": 32}),
                               ("ff_push.pt", {"hidden": 16, "n_links": 1})):  # fmt: skip
        (folder / name).write_bytes(b"")
        (folder / f"{name}.json").write_text(json.dumps({"architecture": architecture}))
    (folder / "obs_noise_push.pt").write_bytes(b"")
    return folder


def test_plan_runs_sets_model_and_selector_per_variant(tmp_path: Path) -> None:
    folder = _checkpoints(tmp_path / "ckpt")
    rect2 = ROOT / "skills/objects/rect2.yaml"
    artic = ROOT / "skills/objects/artic_rect_rect.yaml"
    options = EvalOptions(
        skill=ROOT / "skills/explore_push.yaml", out=tmp_path, checkpoints=folder,
        max_interactions=2, overrides=("components.filter.with.sigma_points=16",
                                       "components.model.with.mirror_average=true"),
    )  # fmt: skip
    plans = plan_runs(options, [rect2, artic], "push")
    assert [(p.spec.name, p.variant.label) for p in plans] == [
        (name, label) for name in ("rect2", "artic_rect_rect")
        for label in ("A-GNN", "U-GNN", "R-GNN", "A-FF", "A-Analytical", "GNN-fixed")
    ]  # fmt: skip
    common = [
        "components.filter.with.sigma_points=16",
        f"components.filter.with.noise_checkpoint={folder / 'obs_noise_push.pt'}",
        "tree.sequence.1.repeat.max=2",
        f"components.world.with.object={rect2}",
    ]
    gnn = 'components.model={"plugin": "filters.gnn", "with": {"checkpoint": "%s", "hidden": 32}}'
    gnn %= folder / "gnn_push.pt"
    ff = ('components.model={"plugin": "filters.ff", "with": {"checkpoints": {"1": "%s"}, '
          '"hidden": 16}}') % (folder / "ff_push.pt")  # fmt: skip
    info_gain = ('components.planner={"plugin": "actions.info_gain", '
                 '"with": {"horizon_s": 2.5, "rate_hz": 15.0}}')  # fmt: skip
    uniform = 'components.planner={"plugin": "actions.uniform"}'
    random = 'components.planner={"plugin": "actions.random"}'
    analytical = 'components.model={"plugin": "filters.analytical"}'
    refined = "components.model.with.mirror_average=true"  # refines each variant's model
    expected = [
        [*common, gnn, refined, info_gain],
        [*common, gnn, refined, uniform],
        [*common, gnn, refined, random],
        [*common, ff, refined, info_gain],
        [*common, analytical, refined, info_gain],
        [*common, gnn, refined, random, "components.filter.with.estimate_parameters=false"],
    ]
    assert [p.overrides for p in plans[:6]] == expected
    # The FF of every link count in the folder: the fit, not the true object, picks one.
    assert [p.overrides[4] for p in plans[6:] if "filters.ff" in p.overrides[4]] == [ff]
    assert all(p.skipped is None for p in plans)
    assert run_dir_of(tmp_path, plans[1]) == tmp_path / "runs/rect2/u-gnn"


def test_the_users_planner_options_and_rate_refine_each_variants_planner(
    tmp_path: Path,
) -> None:
    """``--set components.planner.with.*`` comes after the variant's planner (before, the
    variant's whole planner replaced it) and ``--set rate_hz`` sets info_gain's rate."""
    options = EvalOptions(
        skill=ROOT / "skills/explore_push.yaml", out=tmp_path, variants=("a-gnn", "r-gnn"),
        checkpoints=_checkpoints(tmp_path / "ckpt"),
        overrides=("components.planner.with.horizon_s=1.0", "rate_hz=20"),
    )  # fmt: skip
    plans = plan_runs(options, [ROOT / "skills/objects/rect2.yaml"], "push")
    for plan in plans:
        assert plan.overrides[-1] == "components.planner.with.horizon_s=1.0"
        assert plan.overrides[-2].startswith("components.planner=")
    info_gain = json.loads(plans[0].overrides[-2].split("=", 1)[1])
    assert info_gain["with"]["rate_hz"] == 20.0


def test_the_skills_own_learned_model_options_go_to_the_gnn_and_ff_variants(
    tmp_path: Path,
) -> None:
    folder = _checkpoints(tmp_path / "ckpt")
    skill = tmp_path / "skill.yaml"
    data = yaml.safe_load((ROOT / "skills/explore_pull.yaml").read_text(encoding="utf-8"))
    skill.write_text(yaml.safe_dump(data), encoding="utf-8")
    assert learned_model_options(data) == {"mirror_average": True}
    assert learned_model_options({"components": {"model": {"plugin": "filters.analytical"}}}) == {}
    options = EvalOptions(skill=skill, out=tmp_path, checkpoints=folder,
                          variants=("a-gnn", "a-ff", "a-analytical"))  # fmt: skip
    models = [
        json.loads(override.split("=", 1)[1])
        for plan in plan_runs(options, [ROOT / "skills/objects/rect2.yaml"], "push")
        for override in plan.overrides
        if override.startswith("components.model=")
    ]
    assert [m["plugin"] for m in models] == ["filters.gnn", "filters.ff", "filters.analytical"]
    assert models[0]["with"] == {"mirror_average": True, "checkpoint": str(folder / "gnn_push.pt"),
                                 "hidden": 32}  # fmt: skip
    assert models[1]["with"]["mirror_average"] is True
    assert "with" not in models[2]


def test_variant_choice_and_the_skills_own_info_gain_settings(tmp_path: Path) -> None:
    assert parse_variants(" r-gnn,a-gnn,r-gnn ") == ("r-gnn", "a-gnn")
    options = EvalOptions(
        skill=ROOT / "skills/explore_push.yaml", out=tmp_path, models=("gnn", "analytical"),
        variants=("a-ff", "r-gnn", "a-gnn"),
    )  # fmt: skip
    assert [v.label for v in chosen_variants(options)] == ["A-GNN", "R-GNN"]
    skill = {"rate_hz": 10, "components": {"planner": {"plugin": "actions.info_gain",
                                                       "with": {"horizon_s": 1.0}}}}  # fmt: skip
    assert planner_override("info_gain", skill) == (
        'components.planner={"plugin": "actions.info_gain", "with": {"horizon_s": 1.0}}'
    )
    assert planner_override("info_gain", {"rate_hz": 10}) == (
        'components.planner={"plugin": "actions.info_gain", '
        '"with": {"horizon_s": 2.5, "rate_hz": 10.0}}'
    )


def _record(
    variant: str, m_estimate: float, tracking_m: float, fixed: bool = False
) -> dict[str, Any]:
    pairs = {"m_0": (m_estimate, 1.0), "f_0": (0.3, 0.3)}
    return {
        "object": "rect2", "type": "homogeneous", "kind": "push", "variant": variant,
        "status": "ok", "parameters": pairs, "history": [pairs],
        "tracking": {"position_m": tracking_m, "angle_rad": 0.0, "steps": 10},
        "estimate_parameters": not fixed,
    }  # fmt: skip


def test_normalised_errors_are_in_stds_of_the_matched_link() -> None:
    belief = {
        "m_0": {"mean": 1.2, "std": 0.1}, "f_0": {"mean": 0.3, "std": 0.05},
        "com_x_0": {"mean": 0.01, "std": 0.01}, "com_y_0": {"mean": 0.0, "std": 0.0},
        "f_j_0": {"mean": 0.1, "std": 0.05},
    }  # fmt: skip
    truth = {"m_1": 1.0, "f_1": 0.4, "com_x_1": 0.0, "com_y_1": 0.0, "f_j_0": 0.2}
    entries = normalised_errors(belief, truth, {0: 1})  # com_y has no std: left out
    assert [name for name, _, _ in entries] == ["m_0", "f_0", "com_x_0", "f_j_0"]
    assert [z for _, z, _ in entries] == pytest.approx([2.0, -2.0, 1.0, -2.0])
    assert [std for _, _, std in entries] == pytest.approx([0.1, 0.05, 0.01, 0.05])


def test_log_score_is_the_gaussian_nll_in_range_units() -> None:
    ranges = {"m": 1.4, "f": 0.4, "CoM": 0.05, "f_j": 0.5}
    # std 0.14 kg = a tenth of the mass range, 1 std off: 0.5 + ln 0.1 + ln sqrt(2 pi)
    assert log_score("m_1", 1.0, 0.14, ranges) == pytest.approx(0.5 + math.log(0.1) + 0.9189385)
    assert log_score("com_y_0", 0.0, 0.05, ranges) == pytest.approx(0.9189385)
    assert log_score("f_j_0", 0.0, 0.5, ranges) == pytest.approx(0.9189385)
    # the same error: a belief sure of a wrong value scores worse than an honest one
    error = 0.1
    assert log_score("f_0", error / 0.01, 0.01, ranges) > log_score("f_0", error / 0.1, 0.1, ranges)


def test_tables_have_one_column_per_variant() -> None:
    labels = ["A-GNN", "U-GNN", "R-GNN", "A-FF", "A-Analytical"]
    records = [_record(label, 1.0 + 0.14 * i, 0.001 * (i + 1)) for i, label in enumerate(labels)]
    records.append(_record("GNN-fixed", 0.0, 0.01, fixed=True))
    tables = nrmse_tables(records, RANGES, labels)
    cell = tables["homogeneous"]["push"]
    assert list(cell) == labels
    for i, label in enumerate(labels):
        assert cell[label]["m_0"] == pytest.approx(0.14 * i / 1.4)
        assert cell[label]["overall"] == pytest.approx(0.05 * i)  # mean of m_0 and f_0 (0)
    tracking = tracking_table(records)
    assert list(tracking["all"]) == [*labels, "GNN-fixed"]
    markdown = tables_markdown(tables, tracking)
    assert "| parameter | A-GNN | U-GNN | R-GNN | A-FF | A-Analytical |" in markdown
    assert "| m_0 | 0.000 | 0.100 | 0.200 | 0.300 | 0.400 |" in markdown
    assert "| homogeneous | GNN-fixed | 10.000 | 0.000 | 1 |" in markdown
    for record, z in zip(records, ([0.5, -1.0], [3.0, 1.5], [-2.5, 0.0]), strict=False):
        record["normalised_errors"] = [("m_0", value, 0.14) for value in z]
    for record in records[3:]:
        record["normalised_errors"] = []
    calibration = calibration_table(records, RANGES)
    assert list(calibration) == ["A-GNN", "U-GNN", "R-GNN"]  # (GNN-fixed estimates nothing)
    score = math.log(0.1) + 0.5 * math.log(2 * math.pi) + 0.5 * (3.0**2 + 1.5**2) / 2
    assert calibration["U-GNN"] == pytest.approx(
        {"within_2_std": 0.5, "median_abs_z": 2.25, "log_score": score, "entries": 2.0}
    )
    assert "| R-GNN | 0.500 | 1.250 | " in tables_markdown(tables, tracking, calibration)
    curves = nrmse_by_interaction(records, RANGES, [*labels, "GNN-fixed"])
    assert curves["R-GNN"] == pytest.approx([0.1])
    assert curves["GNN-fixed"] == pytest.approx([0.5 / 1.4])  # m error 1.0 / 1.4, f error 0


def test_mass_and_friction_from_their_product_match_monte_carlo() -> None:
    """E[m | m f] and E[f | m f] for uniform m in [0.2, 1.6] kg and f in [0.1, 0.5], against
    the mean of samples whose product falls in a narrow band; at the corners of the ranges
    the product pins both down."""
    rng = np.random.default_rng(0)
    mass, friction = rng.uniform(0.2, 1.6, 2_000_000), rng.uniform(0.1, 0.5, 2_000_000)
    for product in (0.05, 0.24, 0.5):
        band = np.abs(mass * friction - product) < 0.002
        m_hat, f_hat = product_posterior_mean(product)
        assert m_hat == pytest.approx(mass[band].mean(), rel=0.01)
        assert f_hat == pytest.approx(friction[band].mean(), rel=0.01)
        assert m_hat * f_hat != pytest.approx(product, rel=0.01)  # E[m] E[f] != E[m f]
    assert product_posterior_mean(0.2 * 0.1) == pytest.approx((0.2, 0.1))
    assert product_posterior_mean(1.6 * 0.5) == pytest.approx((1.6, 0.5))


def test_reference_columns_score_the_prior_and_a_known_product() -> None:
    records = [_record("A-GNN", 1.0, 0.001), _record("U-GNN", 1.2, 0.001)]
    records[0]["parameters"] |= {"CoM_0": ((0.02, 0.0), (0.01, 0.03))}
    prior = Prior(mass_kg=(0.5, 0.4), friction=(0.2, 0.1), com_m=(0.0, 0.02))
    references = reference_records(records, prior)
    assert [r["variant"] for r in references] == ["Prior", "m·f known", "load known"]
    truth_m, truth_f = records[0]["parameters"]["m_0"][1], records[0]["parameters"]["f_0"][1]
    assert references[0]["parameters"] == {
        "m_0": (0.5, truth_m), "f_0": (0.2, truth_f), "CoM_0": ((0.0, 0.0), (0.01, 0.03))
    }  # fmt: skip
    known = references[1]["parameters"]
    assert known["CoM_0"] == ((0.01, 0.03), (0.01, 0.03))
    assert (known["m_0"][0], known["f_0"][0]) == product_posterior_mean(truth_m * truth_f)
    tables = nrmse_tables([*records, *references], RANGES, ["A-GNN", "Prior", "m·f known"])
    assert list(tables["homogeneous"]["push"]) == ["A-GNN", "Prior", "m·f known"]
    # A run whose summary kept the belief it started from is scored by that prior.
    records[0]["prior"] = {"m_0": (0.7, truth_m), "f_0": (0.25, truth_f),
                           "CoM_0": ((0.01, 0.0), (0.01, 0.03))}  # fmt: skip
    assert reference_records(records, prior)[0]["parameters"] == records[0]["prior"]


def test_a_run_without_its_episode_data_is_a_clear_error(tmp_path: Path) -> None:
    """Scoring a finished run whose episode data went missing names the file and the fix."""
    summary = {"filter_steps": [{"episode": 0, "time_s": 0.0}], "belief": {}}
    (tmp_path / "episodes" / "0000").mkdir(parents=True)
    with pytest.raises(DataError, match=r"0000/data.npz: no object_pose .*delete .* to run it"):
        first_poses(tmp_path, summary)
    assert first_poses(tmp_path, {"filter_steps": []}) is None  # no steps: nothing to score


def test_paired_eval_filters_the_first_variants_interactions(tmp_path: Path) -> None:
    """--paired: A-Analytical filters A-GNN's recorded pushes (vistac replay) instead of
    choosing its own, so both columns score the same interactions; R-GNN, another selector,
    still runs its own. A second call reuses the replay. A-Physics (``sim.physics``, which
    only replays) filters them too, and with the world's own motion tracks the object."""
    out = tmp_path / "eval"
    args = [
        "-q", "eval", str(ROOT / "skills/explore_push.yaml"), "--out", str(out),
        "--objects", str(ROOT / "skills/objects/rect2.yaml"), "--paired",
        "--variants", "a-gnn,r-gnn,a-analytical,a-physics", "--max-interactions", "1", *FAST,
    ]  # fmt: skip
    assert main(args) == 0
    runs = out / "runs/rect2"
    lead = json.loads((runs / "a-gnn/summary.json").read_text())
    paired_info = json.loads((runs / "a-analytical/run.json").read_text())
    assert paired_info["replay_of"] == str(runs / "a-gnn")
    assert paired_info["config"]["components"]["model"]["plugin"] == "filters.analytical"
    assert not (runs / "a-analytical/episodes").exists()  # the pushes are A-GNN's
    paired = json.loads((runs / "a-analytical/summary.json").read_text())
    assert paired["episodes"] == lead["episodes"] and paired["prior"] == lead["prior"]
    assert paired["belief"] != lead["belief"]
    own = json.loads((runs / "r-gnn/run.json").read_text())
    assert "replay_of" not in own and (runs / "r-gnn/episodes").is_dir()
    report = json.loads((out / "eval.json").read_text(encoding="utf-8"))
    records = {r["variant"]: r for r in report["runs"]}
    assert records["A-Analytical"]["replay_of"] == str(runs / "a-gnn")
    assert records["A-Analytical"]["interactions"] == records["A-GNN"]["interactions"] == 1
    tracking = report["tracking"]["homogeneous"]
    assert math.isfinite(tracking["A-Analytical"]["position_m"])  # against A-GNN's truth
    physics = json.loads((runs / "a-physics/run.json").read_text())
    assert physics["replay_of"] == str(runs / "a-gnn")
    assert physics["config"]["components"]["model"] == {"plugin": "sim.physics"}
    assert tracking["A-Physics"]["position_m"] < max(0.003, 1.5 * tracking["A-GNN"]["position_m"])
    stamp = (runs / "a-analytical/eval_args.json").stat().st_mtime_ns
    assert main(args) == 0
    assert (runs / "a-analytical/eval_args.json").stat().st_mtime_ns == stamp


def test_a_replay_is_reused_only_for_the_same_finished_lead_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The replay's stamp holds the lead's arguments and summary: a lead rerun with another
    seed, or giving other pushes, is replayed again; a failed lead leaves nothing to replay
    (before, the old replay was reused in all three cases). A checkpoint the replay's model
    names, retrained in place, is replayed again too; the lead, which does not name it, is
    reused."""
    import vistac.pluginmanager
    import vistac.replay

    replays: list[Path] = []

    def replay(source: Path, out_dir: Path, *_: Any, **__: Any) -> dict[str, Any]:
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "summary.json").write_text("{}")
        replays.append(source)
        return {}

    monkeypatch.setattr(vistac.replay, "replay", replay)
    monkeypatch.setattr(vistac.pluginmanager, "load_plugins", lambda: None)
    rect2 = ROOT / "skills/objects/rect2.yaml"
    variants = {variant.key: variant for variant in VARIANTS}
    lead = RunPlan(rect2, load_object(rect2), variants["a-gnn"], overrides=["a=1"])
    weights = tmp_path / "ff.pt"
    weights.write_bytes(b"trained once")
    paired = RunPlan(rect2, lead.spec, variants["a-analytical"], lead=lead,
                     overrides=[f"components.model.with.checkpoint={weights}"])  # fmt: skip
    seed_0, seed_1 = (EvalOptions(skill=ROOT / "skills/explore_push.yaml", out=tmp_path,
                                  seed=seed, paired=True) for seed in (0, 1))  # fmt: skip
    runs = fake_run(monkeypatch, 0)
    for options in (seed_0, seed_0, seed_1):
        assert execute(lead, options)["status"] == "ok"
        assert replay_run(paired, options)["status"] == "ok"
    assert len(replays) == 2  # seed 0's replay reused once, then seed 1's lead replayed
    (run_dir_of(tmp_path, lead) / "summary.json").write_text('{"other": "pushes"}')
    assert replay_run(paired, seed_1)["status"] == "ok" and len(replays) == 3
    weights.write_bytes(b"trained again")
    assert execute(lead, seed_1)["status"] == "ok" and len(runs) == 2
    assert replay_run(paired, seed_1)["status"] == "ok" and len(replays) == 4
    fake_run(monkeypatch, 1)
    assert execute(lead, seed_0)["status"] == "failed"
    failed = replay_run(paired, seed_0)
    assert failed["status"] == "failed" and len(replays) == 4
    assert failed["reason"] == "nothing to replay: A-GNN's run failed"


def test_paired_variants_follow_the_first_variant_that_runs(tmp_path: Path) -> None:
    """--paired: GNN-fixed, which estimates no parameters, filters A-GNN's pushes as well
    (before, it ran its own random ones); a variant skipped for want of a checkpoint leads
    none (before, A-Analytical was skipped with the A-GNN it was paired with)."""
    rect2 = ROOT / "skills/objects/rect2.yaml"
    options = EvalOptions(
        skill=ROOT / "skills/explore_push.yaml", out=tmp_path, paired=True,
        checkpoints=_checkpoints(tmp_path / "ckpt"),
        variants=("a-gnn", "r-gnn", "a-analytical", "gnn-fixed"),
    )  # fmt: skip
    leads = {p.variant.key: p.lead and p.lead.variant.key
             for p in plan_runs(options, [rect2], "push")}  # fmt: skip
    assert leads == {"a-gnn": None, "r-gnn": None, "a-analytical": "a-gnn", "gnn-fixed": "a-gnn"}
    (tmp_path / "bare").mkdir()
    bare = replace(options, checkpoints=tmp_path / "bare", variants=("a-gnn", "a-analytical"))
    gnn, analytical = plan_runs(bare, [rect2], "push")
    assert gnn.skipped and analytical.skipped is None
    assert analytical.lead is None


def _scored_object(name: str, variant: str, m_error: float) -> dict[str, Any]:
    record = _record(variant, 1.0 + m_error, 0.001)
    return record | {"object": name}


def test_differences_from_the_first_column_pair_the_objects_and_bound_the_noise() -> None:
    """A column worse by the same error on every object differs by exactly that, with an
    interval of width 0; one that is better on some objects and worse on others gets an
    interval that holds 0; the same seed gives the same interval."""
    errors = [0.1, -0.2, 0.3, -0.1, 0.2, -0.3, 0.05, -0.05]
    records = [_scored_object(f"o{i}", "A-GNN", 0.0) for i in range(8)]
    records += [_scored_object(f"o{i}", "U-GNN", 0.14) for i in range(8)]
    records += [_scored_object(f"o{i}", "R-GNN", e) for i, e in enumerate(errors)]
    records += [_scored_object("o0", "A-FF", 0.5)]  # one object only: no interval
    table = difference_table(records, RANGES, ["A-GNN", "U-GNN", "R-GNN", "A-FF"])
    cell = table["all"]["push"]
    assert list(cell) == ["U-GNN", "R-GNN"]
    # m_0's NRMSE 0.14 / 1.4 = 0.1, f_0's 0: overall 0.05 on every resample.
    assert cell["U-GNN"] == pytest.approx(
        {"difference": 0.05, "low": 0.05, "high": 0.05, "objects": 8.0}
    )
    rmse = math.sqrt(np.mean(np.square(errors)))
    assert cell["R-GNN"]["difference"] == pytest.approx(rmse / 1.4 / 2)
    assert 0.0 < cell["R-GNN"]["low"] < cell["R-GNN"]["difference"] < cell["R-GNN"]["high"]
    assert difference_table(records, RANGES, ["A-GNN", "R-GNN"])["all"]["push"] == {
        "R-GNN": cell["R-GNN"]
    }  # deterministic
    swapped = [_scored_object(f"o{i}", "B", e) for i, e in enumerate(errors[::-1])]
    noisy = difference_table([*records[16:24], *swapped], RANGES, ["R-GNN", "B"])["all"]["push"]
    assert noisy["B"]["difference"] == pytest.approx(0.0)  # the same errors, other objects
    assert noisy["B"]["low"] < 0.0 < noisy["B"]["high"]
    markdown = tables_markdown(
        nrmse_tables(records, RANGES, ["A-GNN", "U-GNN"]), {}, None, table, "A-GNN"
    )
    assert "# Differences from A-GNN (overall NRMSE)" in markdown
    assert "| all | push | U-GNN | +0.050 | [+0.050, +0.050] | 8 |" in markdown
    assert "| objects | interaction | column | difference | 90 % interval | runs |" in markdown


def _eval_folder(path: Path, m_errors: list[float]) -> Path:
    """A `vistac eval` folder whose A-GNN runs have these mass errors (one object each)."""
    runs = [_scored_object(f"o{i}", "A-GNN", e) for i, e in enumerate(m_errors)]
    report = {"variants": {"A-GNN": {"model": "gnn", "selector": "info_gain",
                                     "estimate_parameters": True}},
              "runs": runs, "ranges": RANGES}  # fmt: skip
    path.mkdir()
    (path / "eval.json").write_text(json.dumps(report), encoding="utf-8")
    return path


def test_compare_pairs_two_evaluations_by_object(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`vistac compare BASE OTHER`: OTHER's overall NRMSE minus BASE's per variant, paired by
    object; a folder without an evaluation, or none shared, is a clear error (exit 2)."""
    base = _eval_folder(tmp_path / "base", [0.0, 0.0, 0.0])
    other = _eval_folder(tmp_path / "other", [0.14, 0.14, 0.14, 0.7])  # o3: not in base
    assert main(["compare", str(base), str(other)]) == 0
    out = capsys.readouterr().out
    assert f"# {other} minus {base} (overall NRMSE)" in out
    assert "| all | push | A-GNN | +0.050 | [+0.050, +0.050] | 3 |" in out
    assert main(["compare", str(base), str(tmp_path)]) == 2
    assert "no eval.json; give the --out folder of a `vistac eval`" in capsys.readouterr().err
    lone = _eval_folder(tmp_path / "lone", [0.1])
    assert main(["compare", str(base), str(lone)]) == 2
    assert "share no parameter-estimating variant" in capsys.readouterr().err
    (lone / "eval.json").write_text("{not json", encoding="utf-8")
    assert main(["compare", str(lone), str(base)]) == 2
    assert "eval.json: not a `vistac eval` report" in capsys.readouterr().err
    (lone / "eval.json").write_text('{"skill": "touch.yaml", "records": []}', encoding="utf-8")
    assert main(["compare", str(lone), str(base)]) == 2
    assert "the evaluation of touch.yaml, a touch or goal-push skill; `vistac compare` takes " \
        "two evaluations of a parameter-estimation skill" in capsys.readouterr().err
