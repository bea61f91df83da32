"""Push-level evidence (``filters.dual`` ``push_evidence``): known answers on a toy model."""

from __future__ import annotations

import functools
import math

import pytest
import torch
from conftest import SKILLS, run_vistac
from vistac.plugins.filters.dual import Belief
from vistac.plugins.filters.mirror import mirror_averaged
from vistac.plugins.filters.rollout import (
    PushEvidence,
    end_poses,
    push_update,
    scored_rows,
    with_marginal,
)
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout

LAYOUT = StateLayout(1)
DT_S = 0.1
STEPS = 20
TURN_PER_COM = 4.0
"""rad/s of turn per m of com_y in the toy model."""
SLIDE_PER_COM = 0.0
"""m/s of sideways slide per m of com_x in the toy model (0: com_x is not observable)."""
PROCESS_VAR = (1e-6, 1e-6, 1e-4, 0.0, 0.0, 0.0)


class TurnByCoM:
    """A push that turns the link at ``TURN_PER_COM * com_y + bias_radps`` and slides it
    sideways at ``SLIDE_PER_COM * com_x``: the end pose is linear in the CoM."""

    n_links = 1

    def __init__(self, bias_radps: float = 0.0) -> None:
        self.bias_radps = bias_radps

    def predict(self, states: torch.Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        del inputs
        params = LAYOUT.link_parameters(states)[..., 0, :]
        rate = TURN_PER_COM * params[..., 3] + self.bias_radps
        slide = SLIDE_PER_COM * params[..., 2]
        pose = states[..., :6].clone()
        pose[..., 1] += dt_s * slide
        pose[..., 2] += dt_s * rate
        pose[..., 4], pose[..., 5] = slide, rate
        force = states.new_zeros((*states.shape[:-1], 2))
        return Prediction(pose, force, torch.tensor(PROCESS_VAR, dtype=DTYPE))


def _inputs() -> list[ProcessInput]:
    one = ProcessInput(
        tcp=torch.zeros(6, dtype=DTYPE), pd_rad=torch.tensor(0.0, dtype=DTYPE),
        is_pull=torch.tensor(0.0, dtype=DTYPE), link=torch.tensor(0),
        link_size_m=torch.tensor([[0.06, 0.06]], dtype=DTYPE),
        link_offset=torch.zeros(1, 3, dtype=DTYPE),
    )  # fmt: skip
    return [one] * STEPS


def _belief(com_std_m: float = 0.02) -> Belief:
    """At rest at the origin, m 0.5, f 0.3, CoM N(0, com_std_m^2) per axis."""
    mean = torch.zeros(LAYOUT.size, dtype=DTYPE)
    mean[6:8] = torch.tensor([0.5, 0.3], dtype=DTYPE)
    std = torch.tensor([1e-3, 1e-3, 1e-2, 1e-3, 1e-3, 1e-3, 0.2, 0.1, com_std_m, com_std_m])
    return Belief(mean, torch.diag(std.to(DTYPE) ** 2))


def _rollout(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    return end_poses(TurnByCoM().predict, LAYOUT, states, _inputs(), DT_S, None)


def test_rollout_ends_where_the_rates_take_it_and_sums_the_process_variance() -> None:
    state = _belief().mean.clone()
    state[9] = 0.01
    ends, var = _rollout(state[None])
    assert ends.shape == (1, 1, 3) and var.shape == (1, 1, 3)
    assert float(ends[0, 0, 2]) == pytest.approx(STEPS * DT_S * TURN_PER_COM * 0.01)
    torch.testing.assert_close(var[0, 0], STEPS * torch.tensor(PROCESS_VAR[:3], dtype=DTYPE))


def test_mirror_averaged_rollouts_cancel_a_one_sided_turn() -> None:
    """A model that turns every push 0.3 rad/s to one side: the mirror-averaged rollout
    (push_evidence.mirror_average) ends where the unbiased model does."""
    state = _belief().mean.clone()
    state[9] = 0.01
    biased = TurnByCoM(bias_radps=0.3).predict
    plain, _ = end_poses(biased, LAYOUT, state[None], _inputs(), DT_S, None)
    averaged, _ = end_poses(functools.partial(mirror_averaged, biased), LAYOUT, state[None],
                            _inputs(), DT_S, None)  # fmt: skip
    unbiased = STEPS * DT_S * TURN_PER_COM * 0.01
    assert float(plain[0, 0, 2]) == pytest.approx(unbiased + STEPS * DT_S * 0.3)
    assert float(averaged[0, 0, 2]) == pytest.approx(unbiased)


def test_scored_rows_name_the_parameters() -> None:
    layout = StateLayout(2)
    rows = scored_rows(layout, ("com_", "f_j_"))
    assert [layout.names[i] for i in rows] == ["com_x_0", "com_y_0", "com_x_1", "com_y_1", "f_j_0"]
    assert scored_rows(layout, ("nothing",)) == []


def test_with_marginal_of_a_kalman_posterior_is_the_joint_kalman_posterior() -> None:
    """Measure two entries of a correlated Gaussian: replacing their marginal by its
    posterior and moving the rest by regression is the full Kalman update."""
    generator = torch.Generator().manual_seed(3)
    factor = torch.randn(6, 6, generator=generator, dtype=DTYPE)
    cov = factor @ factor.T + 0.1 * torch.eye(6, dtype=DTYPE)
    prior = Belief(torch.randn(6, generator=generator, dtype=DTYPE), cov)
    rows = [2, 4]
    observe = torch.zeros(2, 6, dtype=DTYPE)
    observe[0, 2], observe[1, 4] = 1.0, 1.0
    noise = torch.diag(torch.tensor([0.3, 0.5], dtype=DTYPE))
    measured = torch.tensor([1.0, -2.0], dtype=DTYPE)
    innovation = observe @ prior.cov @ observe.T + noise
    gain = prior.cov @ observe.T @ torch.linalg.inv(innovation)
    full_mean = prior.mean + gain @ (measured - observe @ prior.mean)
    full_cov = prior.cov - gain @ innovation @ gain.T
    index = torch.tensor(rows)
    moved = with_marginal(prior, rows, full_mean[index], full_cov[index][:, index])
    torch.testing.assert_close(moved.mean, full_mean)
    torch.testing.assert_close(moved.cov, full_cov)
    unchanged = with_marginal(prior, rows, prior.mean[index], prior.cov[index][:, index])
    torch.testing.assert_close(unchanged.mean, prior.mean)
    torch.testing.assert_close(unchanged.cov, prior.cov)


def _update(
    settings: PushEvidence, true_com: tuple[float, float], seed: int = 0, com_std_m: float = 0.02
) -> Belief:
    prior = _belief(com_std_m)
    truth = prior.mean.clone()
    truth[8:10] = torch.tensor(true_com, dtype=DTYPE)
    tracked, _ = _rollout(truth[None])
    after = prior.mean.clone()
    after[:3] = tracked[0, 0]
    belief = Belief(after, prior.cov)
    return push_update(
        belief, prior, LAYOUT, settings, _rollout, torch.tensor([[0.06, 0.06]], dtype=DTYPE),
        torch.Generator().manual_seed(seed),
    )  # fmt: skip


def test_push_update_is_the_bayes_posterior_of_a_linear_model() -> None:
    """End angle = g com_y with g = steps dt k: the posterior of com_y is the Kalman one;
    com_x, which the push does not show, keeps its prior."""
    settings = PushEvidence(enabled=True, samples=4000, min_ess_fraction=0.01,
                            std_floor=(0.001, 0.02))  # fmt: skip
    true_com = (0.015, -0.012)
    posterior = _update(settings, true_com)
    gain_rad_per_m = STEPS * DT_S * TURN_PER_COM
    prior_var, tracked_var = 0.02**2, 2 * 1e-2**2  # start and end pose variance
    noise_var = max(STEPS * PROCESS_VAR[2], 0.02**2) + tracked_var
    kalman_gain = prior_var * gain_rad_per_m / (gain_rad_per_m**2 * prior_var + noise_var)
    want_mean = kalman_gain * gain_rad_per_m * true_com[1]
    want_std = math.sqrt(prior_var - kalman_gain * gain_rad_per_m * prior_var)
    assert float(posterior.mean[9]) == pytest.approx(want_mean, abs=0.1 * want_std)
    assert math.sqrt(float(posterior.cov[9, 9])) == pytest.approx(want_std, rel=0.1)
    assert abs(float(posterior.mean[8])) < 0.1 * 0.02
    assert math.sqrt(float(posterior.cov[8, 8])) == pytest.approx(0.02, rel=0.1)


def test_a_welded_pair_shows_its_combined_com_not_the_split() -> None:
    """Two welded links of equal mass turn together at k times the mean of their com_y: the
    push's posterior of that mean is the Kalman one (both links' end angles measure it, so
    the noise variance halves), and the difference of the two com_y keeps its prior."""
    layout = StateLayout(2)
    var_per_link = (1e-6, 1e-6, 1e-4, 0.0, 0.0, 0.0)

    def predict(states: torch.Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        del inputs
        rate = TURN_PER_COM * layout.link_parameters(states)[..., :, 3].mean(-1)
        pose = layout.link_pose(states).clone()
        pose[..., 2] += dt_s * rate[..., None]
        pose[..., 5] = rate[..., None]
        force = states.new_zeros((*states.shape[:-1], 2))
        return Prediction(pose.flatten(-2), force, torch.tensor(var_per_link * 2, dtype=DTYPE))

    def rollout(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return end_poses(predict, layout, states, _inputs(), DT_S, None)

    mean = torch.zeros(layout.size, dtype=DTYPE)
    mean[[12, 13, 16, 17]] = torch.tensor([0.5, 0.3, 0.5, 0.3], dtype=DTYPE)  # m f per link
    std = torch.full((layout.size,), 1e-3, dtype=DTYPE)
    std[[2, 8]], std[[14, 15, 18, 19]] = 1e-2, 0.02  # link angles; com_x, com_y per link
    prior = Belief(mean, torch.diag(std**2))
    truth = mean.clone()
    truth[[15, 19]] = torch.tensor([-0.020, -0.004], dtype=DTYPE)  # com_y mean -0.012
    tracked, _ = rollout(truth[None])
    after = mean.clone()
    after[[0, 1, 2, 6, 7, 8]] = tracked[0].flatten()
    settings = PushEvidence(enabled=True, samples=4000, min_ess_fraction=0.01,
                            std_floor=(0.001, 0.02))  # fmt: skip
    posterior = push_update(Belief(after, prior.cov), prior, layout, settings, rollout,
                            torch.full((2, 2), 0.06, dtype=DTYPE),
                            torch.Generator().manual_seed(0))  # fmt: skip
    gain_rad_per_m = STEPS * DT_S * TURN_PER_COM
    prior_var = 0.02**2 / 2  # of the mean of two com_y
    noise_var = (max(STEPS * 1e-4, 0.02**2) + 2 * 1e-2**2) / 2
    kalman_gain = prior_var * gain_rad_per_m / (gain_rad_per_m**2 * prior_var + noise_var)
    want_mean = kalman_gain * gain_rad_per_m * -0.012
    want_std = math.sqrt(prior_var - kalman_gain * gain_rad_per_m * prior_var)
    mean_of_pair = 0.5 * (posterior.mean[15] + posterior.mean[19])
    assert float(mean_of_pair) == pytest.approx(want_mean, abs=0.1 * want_std)
    difference = torch.tensor([1.0, -1.0], dtype=DTYPE)
    index = torch.tensor([15, 19])
    assert abs(float(posterior.mean[15] - posterior.mean[19])) < 0.1 * 0.02
    spread_var = float(difference @ posterior.cov[index][:, index] @ difference)
    assert math.sqrt(spread_var) == pytest.approx(math.sqrt(2) * 0.02, rel=0.1)


def test_tempering_limits_what_one_push_may_tell() -> None:
    """With most samples kept (min_ess_fraction 0.8) one push moves the CoM less than
    the untempered posterior, towards the truth."""
    sharp = {"enabled": True, "samples": 256, "std_floor": (0.001, 0.02)}
    free = _update(PushEvidence(**sharp, min_ess_fraction=0.01), (0.0, -0.02))
    held = _update(PushEvidence(**sharp, min_ess_fraction=0.8), (0.0, -0.02))
    assert float(free.mean[9]) < float(held.mean[9]) < 0.0
    assert float(free.cov[9, 9]) < float(held.cov[9, 9]) < 0.02**2


def test_samples_outside_the_footprint_count_for_nothing() -> None:
    """The CoM on the footprint's edge (0.06 m): the posterior is the likelihood cut at the
    edge, whose mean lies about 0.8 of its std inside (without the cut: on the edge)."""
    settings = PushEvidence(enabled=True, samples=4000, min_ess_fraction=0.01,
                            std_floor=(0.001, 0.02))  # fmt: skip
    posterior = _update(settings, (0.0, 0.06), com_std_m=0.05)
    assert 0.05 < float(posterior.mean[9]) < 0.058


def test_the_update_is_deterministic_under_a_seed() -> None:
    settings = PushEvidence(enabled=True)
    one, two = _update(settings, (0.01, 0.01), seed=5), _update(settings, (0.01, 0.01), seed=5)
    assert torch.equal(one.mean, two.mean) and torch.equal(one.cov, two.cov)


def test_objects_with_more_links_than_max_links_are_left_as_they_are() -> None:
    layout = StateLayout(2)
    mean = torch.zeros(layout.size, dtype=DTYPE)
    mean[[12, 13, 16, 17, 20]] = torch.tensor([0.5, 0.3, 0.5, 0.3, 0.2], dtype=DTYPE)  # m f f_j
    belief = Belief(mean, 1e-4 * torch.eye(layout.size, dtype=DTYPE))

    def no_rollout(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raise AssertionError("rolled out")

    sizes = torch.full((2, 2), 0.05, dtype=DTYPE)
    settings = PushEvidence(enabled=True, max_links=1)
    kept = push_update(belief, belief, layout, settings, no_rollout, sizes, torch.Generator())
    assert kept is belief
    with pytest.raises(AssertionError, match="rolled out"):  # two links by default
        push_update(belief, belief, layout, PushEvidence(enabled=True), no_rollout,
                    sizes, torch.Generator())  # fmt: skip


def test_a_belief_mostly_outside_the_footprint_is_left_as_it_is() -> None:
    """Few feasible samples would give the weighted moments a collapsed covariance: with
    more than half of the CoM samples outside the footprint the push's evidence is skipped."""
    prior = _belief(0.05)
    prior.mean[9] = 0.07  # beyond the 0.06 m half extent
    kept = push_update(
        prior, prior, LAYOUT, PushEvidence(enabled=True), _rollout,
        torch.tensor([[0.06, 0.06]], dtype=DTYPE), torch.Generator().manual_seed(0),
    )  # fmt: skip
    assert kept is prior


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("components.filter.with.push_evidence.parameters=[comx]", "'comx' starts no parameter"),
        ("components.filter.with.push_evidence.std_floor=[0.01, 0]", "greater than 0"),
        ("components.filter.with.push_evidence.sample=10", "did you mean 'samples'"),
    ],
)
def test_bad_settings_are_refused_with_their_path(override: str, message: str) -> None:
    result = run_vistac("validate", str(SKILLS / "explore_push.yaml"), "--set", override)
    assert result.returncode == 2
    assert "components.filter.with.push_evidence" in result.stderr and message in result.stderr
