"""The Bayes estimate of a welded pair's parameters from its friction load and load centre
(the ``load known`` reference of ``vistac eval``)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from vistac.objects import COM_SHRINK, attachment, load_object, uniform_inside
from vistac.plugins.filters.component import Prior
from vistac.plugins.filters.evaluate import (
    largest_bends_rad,
    load_known_pairs,
    nrmse_tables,
    product_known_pairs,
    reference_records,
)
from vistac.plugins.filters.identifiable import (
    pair_load,
    welded_pair_posterior,
    welded_pair_samples,
)

SKILLS = Path(__file__).resolve().parents[1] / "skills"
PAIR = SKILLS / "objects" / "hetero_rect_tri.yaml"


def test_every_weighted_draw_has_the_pairs_load_and_load_centre() -> None:
    spec = load_object(PAIR)
    samples = welded_pair_samples(spec, 20_000, np.random.default_rng(0))
    kept = samples.weight > 0
    assert 0.05 < kept.mean() < 1 and samples.weight.sum() == pytest.approx(1.0)
    offset, _ = attachment(spec)
    loads = samples.mass_kg[kept] * samples.friction[kept]  # [n, 2]
    centres = samples.com_m[kept] + np.stack([np.zeros(2), offset])  # [n, 2, 2]
    load, centre = pair_load(spec)
    np.testing.assert_allclose(loads.sum(axis=1), load, rtol=1e-12)
    centre_of_draws = np.einsum("nl,nlc->nc", loads, centres) / loads.sum(axis=1)[:, None]
    np.testing.assert_allclose(centre_of_draws, np.broadcast_to(centre, centre_of_draws.shape),
                               atol=1e-12)  # fmt: skip
    assert samples.friction[kept].min() >= 0.1 and samples.friction[kept].max() <= 0.5


def test_the_posterior_matches_rejection_sampling_of_the_prior() -> None:
    """Draws of the whole prior whose load lies within 1 % and whose load centre lies within
    2 mm of the pair's: their means are the posterior's, up to their sampling error (about
    0.04 kg, 0.011 and 1-2 mm with some 100 draws kept). Without the Jacobian weights the
    mass of link 1 comes out 0.25 kg higher, with 1 / m_1 alone link 0's CoM 7 mm off."""
    spec = load_object(PAIR)
    load, centre = pair_load(spec)
    offset, _ = attachment(spec)
    rng = np.random.default_rng(1)
    count = 4_000_000
    mass, friction = rng.uniform(0.2, 1.6, (count, 2)), rng.uniform(0.1, 0.5, (count, 2))
    com_0 = uniform_inside(COM_SHRINK * spec.links[0].polygon(), count, rng)
    com_1 = uniform_inside(COM_SHRINK * spec.links[1].polygon(), count, rng)
    loads = mass * friction
    centres = (loads[:, :1] * com_0 + loads[:, 1:] * (com_1 + offset)) / loads.sum(1)[:, None]
    near = (np.abs(loads.sum(1) - load) < 0.01 * load) & (
        np.linalg.norm(centres - centre, axis=1) < 0.002
    )
    assert near.sum() > 60
    posterior = welded_pair_posterior(spec)
    np.testing.assert_allclose([m for m, _, _ in posterior], mass[near].mean(0), atol=0.06)
    np.testing.assert_allclose([f for _, f, _ in posterior], friction[near].mean(0), atol=0.02)
    np.testing.assert_allclose(posterior[0][2], com_0[near].mean(0), atol=0.003)


def test_a_load_near_its_largest_pins_mass_and_friction_near_theirs() -> None:
    spec = load_object(PAIR)
    links = [link.model_copy(update={"mass_kg": 1.55, "friction": 0.48}) for link in spec.links]
    posterior = welded_pair_posterior(spec.model_copy(update={"links": links}), 50_000)
    for mass, friction, _ in posterior:
        assert mass > 1.4 and friction > 0.43
    with pytest.raises(ValueError, match="2 links"):
        welded_pair_samples(load_object(SKILLS / "objects" / "rect2.yaml"), 10,
                            np.random.default_rng(0))  # fmt: skip


def _pair_record() -> dict[str, object]:
    """A scored run of the welded pair: rows named by the true link."""
    spec = load_object(PAIR)
    truth: dict[str, object] = {}
    for index, link in enumerate(spec.links):
        truth |= {f"m_{index}": (0.9, link.mass_kg), f"f_{index}": (0.3, link.friction),
                  f"CoM_{index}": ((0.0, 0.0), (0.02, -0.01))}  # fmt: skip
    return {"object": spec.name, "object_file": str(PAIR), "type": "heterogeneous",
            "kind": "push", "variant": "A-GNN", "status": "ok", "estimate_parameters": True,
            "links": {"0": 1, "1": 0}, "parameters": truth}  # fmt: skip


def test_load_known_scores_each_true_link_by_its_posterior() -> None:
    """Rows are named by the true link whatever the belief's numbering (``links``)."""
    spec = load_object(PAIR)
    posterior = welded_pair_posterior(spec)
    pairs = load_known_pairs(_pair_record())
    assert pairs is not None
    assert pairs["m_0"] == (posterior[0][0], spec.links[0].mass_kg)
    assert pairs["f_1"] == (posterior[1][1], spec.links[1].friction)
    estimate, truth = pairs["CoM_1"]
    error = np.asarray(posterior[1][2]) - np.asarray(spec.links[1].com_m)
    assert math.dist(estimate, truth) == pytest.approx(float(np.linalg.norm(error)))
    single = _pair_record() | {"type": "homogeneous"}
    assert load_known_pairs(single) == product_known_pairs(single["parameters"])  # type: ignore[arg-type]
    assert load_known_pairs(_pair_record() | {"object_file": "/no/such.yaml"}) is None


def test_the_load_known_column_leaves_a_welded_pairs_coms_open() -> None:
    """Among the references of a heterogeneous run, next to *m·f known* (each CoM exact);
    left out when the run names no object file."""
    record = _pair_record()
    references = reference_records([record], Prior())
    assert [r["variant"] for r in references] == ["Prior", "m·f known", "load known"]
    ranges = {"m": 1.4, "f": 0.4, "CoM": 0.088, "f_j": 0.5}
    cell = nrmse_tables(references, ranges, ["m·f known", "load known"])["heterogeneous"]["push"]
    assert cell["m·f known"]["CoM_0"] == 0 < cell["load known"]["CoM_0"]
    without_file = reference_records([record | {"object_file": None}], Prior())
    assert [r["variant"] for r in without_file] == ["Prior", "m·f known"]


ARTICULATED = SKILLS / "objects" / "artic_rect_rect.yaml"


def _hinged_record(bend_rad: float) -> dict[str, object]:
    """A scored run of the hinged pair whose hinge turned at most ``bend_rad``."""
    spec = load_object(ARTICULATED)
    truth: dict[str, object] = {"f_j_0": (0.2, spec.joint.friction_nm)}
    for index, link in enumerate(spec.links):
        truth |= {f"m_{index}": (0.9, link.mass_kg), f"f_{index}": (0.3, link.friction),
                  f"CoM_{index}": ((0.0, 0.0), (0.02, -0.01))}  # fmt: skip
    return _pair_record() | {"object": spec.name, "object_file": str(ARTICULATED),
                             "type": "articulated", "parameters": truth,
                             "joint_bends_rad": [bend_rad]}  # fmt: skip


def test_a_hinge_that_held_leaves_the_pair_as_open_as_a_welded_one() -> None:
    """A hinged pair moves as one rigid body while its hinge holds: *load known* gives the
    welded pair's posterior and the prior's joint friction; once the hinge turned, each
    link's load (as *m·f known*)."""
    spec = load_object(ARTICULATED)
    posterior = welded_pair_posterior(spec)
    held = _hinged_record(math.radians(1.0))
    pairs = load_known_pairs(held, Prior(joint_friction_nm=(0.3, 0.1)))
    assert pairs is not None
    assert pairs["m_1"] == (posterior[1][0], spec.links[1].mass_kg)
    assert pairs["f_j_0"] == (0.3, spec.joint.friction_nm)
    turned = _hinged_record(math.radians(10.0))
    assert load_known_pairs(turned) == product_known_pairs(turned["parameters"])
    unknown = _hinged_record(0.0) | {"joint_bends_rad": []}  # scored before bends were kept
    assert load_known_pairs(unknown) == product_known_pairs(unknown["parameters"])


def test_the_largest_bend_is_over_every_step_of_every_episode(tmp_path: Path) -> None:
    """From the run's first step, wrapped: a pair starting at 3.1 rad apart that turns to
    -3.1 rad has turned 0.083 rad, not 6.2."""
    bends_by_episode = ([3.1, 3.12, 3.13], [3.13, -3.1, 3.05])
    for index, bends in enumerate(bends_by_episode):
        pose = np.zeros((len(bends), 2, 3))
        pose[:, 0, 2] = 0.5
        pose[:, 1, 2] = 0.5 + np.asarray(bends)
        folder = tmp_path / "episodes" / f"{index:04d}"
        folder.mkdir(parents=True)
        np.savez(folder / "data.npz", object_pose=pose)
    (bend,) = largest_bends_rad(tmp_path)
    assert bend == pytest.approx(2 * math.pi - 6.2)
    assert largest_bends_rad(tmp_path / "nothing") == []
