"""Known-answer tests of the dual differentiable filter's numerical core."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.typing import NDArray
from torch import Tensor
from vistac.errors import DataError
from vistac.plugins.filters.dual import (
    Belief,
    DualFilter,
    ParameterFit,
    antithetic_noise,
    bound_twist,
    cholesky_safe,
    feasible,
    iid_fit_noise,
    liu_west,
    marginal_inverse_var,
    marginal_log_likelihood,
    on_load_ridge,
    paired_fit_noise,
    parameter_fit,
    project_feasible,
    require_finite,
    sample_sigma_points,
    standardise_noise,
    truncate_negative_means,
    unscented_points,
    weighted_moments,
    woodbury_update,
)
from vistac.plugins.filters.state import DTYPE, Prediction, ProcessInput, StateLayout

LAYOUT = StateLayout(1)
DT_S = 0.1
ACCEL_GAIN = np.array([[-1.0, 2.0, 0.0, 0.0], [0.5, 0.0, 3.0, 0.0], [0.0, -1.0, 0.0, 5.0]])
"""Acceleration (vx, vy, omega) per parameter (m, f, com_x, com_y) of the linear toy."""
ACCEL_OFFSET = np.array([0.2, -0.1, 0.0])
FORCE_GAIN = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 2.0, 0.0, 0.0]])
"""Tactile force (N) per parameter: depends on the parameters only, so the toy is exact."""
PROCESS_VAR = np.array([1e-6, 1e-6, 1e-6, 1e-4, 1e-4, 1e-4])
POSITION_VAR = 1e-4
FORCE_VAR = 4e-2
TRUE_PARAMETERS = np.array([1.0, 0.5, 0.01, -0.02])
PRIOR_MEAN = np.array([0, 0, 0, 0, 0, 0, 0.8, 0.6, 0.0, 0.0])
PRIOR_VAR = np.array([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3, 0.1**2, 0.1**2, 0.02**2, 0.02**2])


pytestmark = pytest.mark.usefixtures("single_thread")


def as_tensor(values: NDArray[np.float64] | list[float]) -> Tensor:
    return torch.as_tensor(np.asarray(values), dtype=DTYPE)


class LinearProcess:
    """x' = x + dt v, v' = v + dt (A phi + c); force = F phi; parameters unchanged."""

    def __init__(self, accel_gain: Tensor | None = None) -> None:
        self.accel_gain = as_tensor(ACCEL_GAIN) if accel_gain is None else accel_gain
        self.calls: list[Tensor] = []

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        self.calls.append(states.detach().clone())
        position, velocity = states[..., 0:3], states[..., 3:6]
        parameters = states[..., 6:10]
        accel = parameters @ self.accel_gain.T + as_tensor(ACCEL_OFFSET)
        pose = torch.cat([position + dt_s * velocity, velocity + dt_s * accel], -1)
        force_n = parameters @ as_tensor(FORCE_GAIN).T
        return Prediction(pose, force_n, as_tensor(PROCESS_VAR))


class LinearObservation:
    """z = (x, y, theta, fx, fy) with diagonal noise."""

    def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
        return torch.cat([states[..., 0:3], force_n], -1)

    def noise_var(self, observation: Tensor) -> Tensor:
        noise = as_tensor([POSITION_VAR] * 3 + [FORCE_VAR] * 2)
        return noise.expand(observation.shape).clone()


def make_inputs(batch: tuple[int, ...] = (), half_extent_m: float = 0.5) -> ProcessInput:
    zeros = torch.zeros(batch, dtype=DTYPE)
    return ProcessInput(
        tcp=torch.zeros((*batch, 6), dtype=DTYPE),
        pd_rad=zeros,
        is_pull=zeros,
        link=torch.zeros(batch, dtype=torch.int64),
        link_size_m=torch.full((*batch, 1, 2), half_extent_m, dtype=DTYPE),
        link_offset=torch.zeros((*batch, 1, 3), dtype=DTYPE),
    )


def prior_belief() -> Belief:
    return Belief(as_tensor(PRIOR_MEAN), torch.diag(as_tensor(PRIOR_VAR)))


@dataclass
class JointSystem:
    """The toy as one linear system s' = Phi s + b + q, z = H s + r."""

    transition: NDArray[np.float64]
    offset: NDArray[np.float64]
    process_cov: NDArray[np.float64]
    observation: NDArray[np.float64]
    noise_cov: NDArray[np.float64]


def joint_system() -> JointSystem:
    transition = np.eye(10)
    transition[0:3, 3:6] = DT_S * np.eye(3)
    transition[3:6, 6:10] = DT_S * ACCEL_GAIN
    offset = np.concatenate([np.zeros(3), DT_S * ACCEL_OFFSET, np.zeros(4)])
    observation = np.zeros((5, 10))
    observation[0:3, 0:3] = np.eye(3)
    observation[3:5, 6:10] = FORCE_GAIN
    return JointSystem(
        transition=transition,
        offset=offset,
        process_cov=np.diag(np.concatenate([PROCESS_VAR, np.zeros(4)])),
        observation=observation,
        noise_cov=np.diag([POSITION_VAR] * 3 + [FORCE_VAR] * 2),
    )


def simulate(system: JointSystem, steps: int, seed: int) -> NDArray[np.float64]:
    """Observations [steps, 5] of a true trajectory starting at rest."""
    rng = np.random.default_rng(seed)
    state = np.concatenate([np.zeros(6), TRUE_PARAMETERS])
    observations = []
    for _ in range(steps):
        noise = rng.multivariate_normal(np.zeros(10), system.process_cov)
        state = system.transition @ state + system.offset + noise
        z_noise = rng.multivariate_normal(np.zeros(5), system.noise_cov)
        observations.append(system.observation @ state + z_noise)
    return np.array(observations)


def kalman_filter(
    system: JointSystem, observations: NDArray[np.float64]
) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """Plain Kalman filter on the joint state: (mean, cov) after each step."""
    mean, cov = PRIOR_MEAN.astype(float), np.diag(PRIOR_VAR)
    history = []
    for z in observations:
        mean = system.transition @ mean + system.offset
        cov = system.transition @ cov @ system.transition.T + system.process_cov
        innovation_cov = system.observation @ cov @ system.observation.T + system.noise_cov
        gain = np.linalg.solve(innovation_cov, system.observation @ cov).T
        mean = mean + gain @ (z - system.observation @ mean)
        cov = cov - gain @ innovation_cov @ gain.T
        history.append((mean, cov))
    return history


EXACT = {"min_ess_fraction": 0.0, "marginal_parameter_likelihood": False, "pose_std_floor": None}
"""The textbook filter (eq. 31 weights, no pose floor): the one that matches the Kalman step."""


def toy_filter(sigma_points: int, process: LinearProcess | None = None) -> DualFilter:
    return DualFilter(
        LAYOUT, process or LinearProcess(), LinearObservation(), sigma_points, **EXACT
    )


@pytest.mark.parametrize("step", [0, 10, 40])
def test_one_step_from_a_kalman_posterior_matches_the_kalman_step(step: int) -> None:
    """Monte-Carlo error only: means within 0.1 KF std, standard deviations within 5 %."""
    system = joint_system()
    observations = simulate(system, steps=step + 1, seed=3)
    reference = kalman_filter(system, observations)
    start = prior_belief()
    if step > 0:
        start = Belief(as_tensor(reference[step - 1][0]), as_tensor(reference[step - 1][1]))
    generator = torch.Generator().manual_seed(step)
    belief = toy_filter(sigma_points=20000).step(
        start, make_inputs(), DT_S, as_tensor(observations[step]), generator
    )
    kf_mean, kf_cov = reference[step]
    kf_std = np.sqrt(np.diag(kf_cov))
    assert np.all(np.abs(belief.mean.numpy() - kf_mean) < 0.1 * kf_std)
    assert np.all(np.abs(np.sqrt(np.diag(belief.cov.numpy())) / kf_std - 1) < 0.05)


def test_linear_gaussian_toy_tracks_the_joint_kalman_filter_for_50_steps() -> None:
    """Tolerances in KF standard deviations, about 1.5 times the worst of seeds 11-15. The
    static parameters accumulate the per-step Monte-Carlo error (0.03 std at C = 2000) and
    pass it to the velocities; the positions forget it."""
    system = joint_system()
    observations = simulate(system, steps=50, seed=3)
    reference = kalman_filter(system, observations)
    dual = toy_filter(sigma_points=4000)
    generator = torch.Generator().manual_seed(11)
    belief, inputs = prior_belief(), make_inputs()
    for z, (kf_mean, kf_cov) in zip(observations, reference, strict=True):
        belief = dual.step(belief, inputs, DT_S, as_tensor(z), generator)
        kf_std = np.sqrt(np.diag(kf_cov))
        mean_error = np.abs(belief.mean.numpy() - kf_mean) / kf_std
        std_error = np.abs(np.sqrt(np.diag(belief.cov.numpy())) / kf_std - 1)
        assert mean_error[:6].max() < 0.6 and mean_error[6:].max() < 1.2, mean_error
        assert std_error[:6].max() < 0.1 and std_error[6:].max() < 0.35, std_error
    final_error = np.abs(belief.mean.numpy()[6:8] - TRUE_PARAMETERS[:2])
    assert np.all(final_error < 3 * np.sqrt(np.diag(reference[-1][1])[6:8]))


def test_liu_west_keeps_the_weighted_particle_moments() -> None:
    generator = torch.Generator().manual_seed(0)
    particles = torch.randn(3, 500, 4, generator=generator, dtype=DTYPE) * 2.0 + 1.0
    weights = torch.softmax(torch.randn(3, 500, generator=generator, dtype=DTYPE), -1)
    expected_mean = (weights[..., None] * particles).sum(-2)
    deviation = particles - expected_mean[..., None, :]
    expected_cov = torch.einsum("bc,bci,bcj->bij", weights, deviation, deviation)
    for delta in (0.5, 0.97, 1.0):
        mean, cov = liu_west(particles, weights, delta)
        torch.testing.assert_close(mean, expected_mean, rtol=0, atol=1e-12)
        torch.testing.assert_close(cov, expected_cov, rtol=0, atol=1e-12)


def random_spd(size: int, generator: torch.Generator) -> Tensor:
    root = torch.randn(size, size, generator=generator, dtype=DTYPE)
    return root @ root.T + 0.1 * torch.eye(size, dtype=DTYPE)


@pytest.mark.parametrize("kappa", [0.0, 1.0, 3.0])
def test_woodbury_update_equals_the_dense_update(kappa: float) -> None:
    generator = torch.Generator().manual_seed(1)
    d, k = 6, 30
    mean = torch.randn(2, d, generator=generator, dtype=DTYPE)
    cov = torch.stack([random_spd(d, generator), random_spd(d, generator)])
    points, weights = unscented_points(mean, torch.linalg.cholesky(cov), kappa)
    gain = torch.randn(k, d, generator=generator, dtype=DTYPE)
    expected = torch.sin(points @ gain.T)
    expected_mean = (weights[:, None] * expected).sum(-2)
    observation = torch.randn(2, k, generator=generator, dtype=DTYPE)
    noise_var = torch.rand(2, k, generator=generator, dtype=DTYPE) + 0.05
    state_dev, obs_dev = points - mean[..., None, :], expected - expected_mean[..., None, :]
    innovation = observation - expected_mean
    post_mean, post_cov = woodbury_update(mean, state_dev, obs_dev, weights, innovation, noise_var)
    innovation_cov = obs_dev.mT @ (weights[:, None] * obs_dev) + torch.diag_embed(noise_var)
    cross_cov = state_dev.mT @ (weights[:, None] * obs_dev)
    kalman_gain = torch.linalg.solve(innovation_cov, cross_cov.mT).mT
    dense_mean = mean + (kalman_gain @ innovation[..., None]).squeeze(-1)
    dense_cov = cov - kalman_gain @ innovation_cov @ kalman_gain.mT
    torch.testing.assert_close(post_mean, dense_mean, rtol=0, atol=1e-9)
    torch.testing.assert_close(post_cov, dense_cov, rtol=0, atol=1e-9)


def test_infeasible_points_never_reach_the_model_but_count_in_the_moments() -> None:
    process = LinearProcess()
    dual = toy_filter(sigma_points=400, process=process)
    mean = as_tensor(PRIOR_MEAN.copy())
    mean[6:10] = as_tensor([0.05, 0.05, 0.09, -0.09])
    variance = as_tensor(PRIOR_VAR.copy())
    variance[6:10] = 0.1**2
    belief, inputs = Belief(mean, torch.diag(variance)), make_inputs(half_extent_m=0.1)
    belief_pred, sigma_pred, _ = dual.predict(
        belief, inputs, DT_S, torch.Generator().manual_seed(5)
    )
    sigma = sample_sigma_points(belief, 400, torch.Generator().manual_seed(5))
    (model_states,) = process.calls
    assert feasible(model_states, LAYOUT, inputs.link_size_m).all()
    is_feasible = feasible(sigma, LAYOUT, inputs.link_size_m)
    assert 0.2 < (~is_feasible).double().mean() < 0.95
    torch.testing.assert_close(model_states[is_feasible], sigma[is_feasible], rtol=0, atol=1e-12)
    torch.testing.assert_close(sigma_pred[..., 6:], sigma[..., 6:], rtol=0, atol=1e-12)
    assert (sigma_pred[..., 6] <= 0).any()
    uniform = torch.full((400,), 1 / 400, dtype=DTYPE)
    moments = weighted_moments(sigma_pred, uniform)
    torch.testing.assert_close(belief_pred.mean, moments[0], rtol=0, atol=1e-14)
    torch.testing.assert_close(belief_pred.cov, moments[1], rtol=0, atol=1e-14)
    # The predicted parameter moments are the belief's, exactly (static parameters).
    torch.testing.assert_close(belief_pred.mean[6:], belief.mean[6:], rtol=0, atol=1e-14)
    torch.testing.assert_close(belief_pred.cov[6:, 6:], belief.cov[6:, 6:], rtol=0, atol=1e-14)


@pytest.mark.parametrize("sigma_points", [16, 100])
def test_an_uninformative_observation_keeps_the_parameter_belief_for_500_steps(
    sigma_points: int,
) -> None:
    """Weights 1/C leave the parameters where they were: raw draws would move the mean by
    their sample error and shrink the covariance by 1 - 1/C per step on average (a collapse
    within a few hundred steps)."""

    class Uninformative(LinearObservation):
        def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
            return torch.zeros(*states.shape[:-1], 5, dtype=DTYPE)

    dual = DualFilter(LAYOUT, LinearProcess(), Uninformative(), sigma_points)
    generator = torch.Generator().manual_seed(3)
    belief, inputs = prior_belief(), make_inputs()
    for _ in range(500):
        belief = dual.step(belief, inputs, DT_S, torch.zeros(5, dtype=DTYPE), generator)
    torch.testing.assert_close(belief.mean[6:], as_tensor(PRIOR_MEAN[6:]), rtol=0, atol=1e-9)
    # (plus the parameter_var_floor of 1e-12 per step)
    torch.testing.assert_close(belief.cov[6:, 6:], prior_belief().cov[6:, 6:], rtol=0, atol=1e-9)


def assert_standard_moments(noise: Tensor) -> None:
    """Sample mean exactly 0 and covariance exactly I of noise [B, C, n]."""
    batch, count, size = noise.shape
    mean, cov = weighted_moments(noise, torch.full((batch, count), 1 / count, dtype=DTYPE))
    torch.testing.assert_close(mean, torch.zeros(batch, size, dtype=DTYPE), rtol=0, atol=1e-13)
    eye = torch.eye(size, dtype=DTYPE).expand(batch, -1, -1)
    torch.testing.assert_close(cov, eye, rtol=0, atol=1e-12)


def test_standardised_noise_has_zero_mean_and_unit_covariance_when_it_can() -> None:
    draws = torch.randn(3, 50, 10, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    assert_standard_moments(standardise_noise(draws))
    few = draws[:, :8]  # C = 8 draws cannot span 10 dimensions
    torch.testing.assert_close(standardise_noise(few), few, rtol=0, atol=0)


def test_antithetic_noise_has_exact_moments_zero_odd_moments_and_a_stable_prefix() -> None:
    draws = torch.randn(3, 60, 10, generator=torch.Generator().manual_seed(1), dtype=DTYPE)
    noise = antithetic_noise(draws)
    assert_standard_moments(noise)
    third = torch.einsum("bci,bcj,bck->bijk", noise, noise, noise)
    torch.testing.assert_close(third, torch.zeros_like(third), rtol=0, atol=1e-12)
    # the first columns do not depend on the columns drawn behind them
    torch.testing.assert_close(antithetic_noise(draws[..., :4]), noise[..., :4], rtol=0, atol=1e-12)
    # too few pairs to span the space, or an odd count: plain standardisation
    torch.testing.assert_close(antithetic_noise(draws[:, :15]), standardise_noise(draws[:, :15]))
    torch.testing.assert_close(antithetic_noise(draws[:, :59]), standardise_noise(draws[:, :59]))


class Edges:
    """400 soft steps of the pose (like pixels at an object's edges): the parameters do not
    show in them."""

    def __init__(self) -> None:
        generator = torch.Generator().manual_seed(0)
        self.gain = torch.randn(400, 3, generator=generator, dtype=DTYPE)
        self.offset_m = 0.01 * torch.randn(400, generator=generator, dtype=DTYPE)

    def expected(self, states: Tensor, force_n: Tensor | None) -> Tensor:
        return torch.sigmoid((states[..., 0:3] @ self.gain.T - self.offset_m) / 0.003)

    def noise_var(self, observation: Tensor) -> Tensor:
        return torch.full(observation.shape, 0.01, dtype=DTYPE)


def test_an_observation_of_the_pose_alone_leaves_the_parameter_belief_about_as_it_was() -> None:
    """The pose scatter of the points makes the pixels differ from point to point; fitted on
    100 points that scatter used to read as information about the parameters and shrank
    their std to 2-6 % of the prior's in 300 steps (and moved the mean by up to 1.4 std).
    Sharp edges at full evidence (no tempering by ``evidence_scale``) are the hard case:
    about half the std is left now."""
    blind = LinearProcess(accel_gain=torch.zeros(3, 4, dtype=DTYPE))
    dual = DualFilter(LAYOUT, blind, Edges(), 100)
    generator = torch.Generator().manual_seed(3)
    belief, inputs = prior_belief(), make_inputs()
    observation = Edges().expected(torch.zeros(10, dtype=DTYPE), None)
    for _ in range(300):
        belief = dual.step(belief, inputs, DT_S, observation, generator)
    prior = prior_belief()
    std_ratio = (belief.cov.diagonal()[6:] / prior.cov.diagonal()[6:]).sqrt()
    assert bool((std_ratio > 0.4).all()), std_ratio
    shift = (belief.mean[6:] - prior.mean[6:]) / prior.cov.diagonal()[6:].sqrt()
    assert bool((shift.abs() < 1.2).all()), shift


class EdgesAndForce(Edges):
    """``Edges`` and the model's force: 400 pixels of the pose alone, then 2 force entries."""

    def expected(self, states: Tensor, force_n: Tensor | None) -> Tensor:
        assert force_n is not None
        return torch.cat([super().expected(states, None), force_n], -1)

    def noise_var(self, observation: Tensor) -> Tensor:
        noise = super().noise_var(observation)
        noise[..., -2:] = FORCE_VAR
        return noise


def test_the_pixels_fit_noise_leaves_the_forces_evidence_whole() -> None:
    """Beside 400 pixels whose fit noise is removed, the force entries alone inform the
    parameters (m and f, force gains 1 and 2): the belief follows the Kalman posterior of the
    forces alone. With the pixels' noise taken from the forces' evidence too, m and f kept
    1.8 and 1.7 times the Kalman std after 20 steps."""
    blind = LinearProcess(accel_gain=torch.zeros(3, 4, dtype=DTYPE))
    dual = DualFilter(LAYOUT, blind, EdgesAndForce(), 100)
    generator = torch.Generator().manual_seed(3)
    belief, inputs, steps = prior_belief(), make_inputs(), 20
    force_n = as_tensor(FORCE_GAIN @ TRUE_PARAMETERS)
    observation = torch.cat([Edges().expected(torch.zeros(10, dtype=DTYPE), None), force_n])
    for _ in range(steps):
        belief = dual.step(belief, inputs, DT_S, observation, generator)
    gain = FORCE_GAIN[[0, 1], [0, 1]]
    precision = 1 / PRIOR_VAR[6:8] + steps * gain**2 / FORCE_VAR
    kalman_mean = PRIOR_MEAN[6:8] / PRIOR_VAR[6:8] + steps * gain * force_n.numpy() / FORCE_VAR
    kalman_mean, kalman_std = kalman_mean / precision, precision**-0.5
    ratio = belief.cov.diagonal()[6:8].sqrt().numpy() / kalman_std
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    assert np.all(np.abs(belief.mean[6:8].numpy() - kalman_mean) < kalman_std), belief.mean[6:8]


def test_on_load_ridge_keeps_each_load_at_the_mean_ratio_in_pushes_only() -> None:
    layout = StateLayout(2)
    generator = torch.Generator().manual_seed(4)
    states = torch.rand(2, 50, layout.size, generator=generator, dtype=DTYPE) + 0.1
    reference = torch.rand(2, layout.size, generator=generator, dtype=DTYPE) + 0.1
    push = torch.tensor([True, False])
    moved = on_load_ridge(states, layout, reference, push)
    before, after = layout.link_parameters(states)[0], layout.link_parameters(moved)[0]
    mean = layout.link_parameters(reference)[0]
    torch.testing.assert_close(after[..., 0] * after[..., 1], before[..., 0] * before[..., 1])
    torch.testing.assert_close(
        after[..., 0] / after[..., 1], (mean[:, 0] / mean[:, 1]).expand(50, 2)
    )
    torch.testing.assert_close(after[..., 2:], before[..., 2:], rtol=0, atol=0)
    torch.testing.assert_close(moved[1], states[1], rtol=0, atol=0)  # the pull
    pose_and_joints = [*range(layout.n_pose), layout.size - 1]
    torch.testing.assert_close(moved[..., pose_and_joints], states[..., pose_and_joints])
    # a batch of pushes only, or of pulls only, as each element of the mixed batch
    only_push = on_load_ridge(states[:1], layout, reference[:1], push[:1])
    torch.testing.assert_close(only_push, moved[:1], rtol=0, atol=0)
    only_pull = on_load_ridge(states[1:], layout, reference[1:], push[1:])
    torch.testing.assert_close(only_pull, states[1:], rtol=0, atol=0)


class MassOnlyForce(LinearProcess):
    """A model that tells m from f apart: the force is 2 m, whatever f is (and the motion
    does not depend on the parameters)."""

    def __init__(self) -> None:
        super().__init__(torch.zeros(3, 4, dtype=DTYPE))

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        prediction = super().predict(states, inputs, dt_s)
        force_n = torch.stack([2.0 * states[..., 6], torch.zeros_like(states[..., 6])], -1)
        return replace(prediction, force_n=force_n)


@pytest.mark.parametrize("load_only", [False, True])
def test_push_load_only_turns_what_a_model_tells_of_m_apart_into_the_load(
    load_only: bool,
) -> None:
    """Fed a force of 2.4 N, a mass-only model moves m alone; seeing the points at the mean's
    ratio m / f, it can only move the load, so m and f rise together (the pull stays m-only)."""
    observation = as_tensor([0.0, 0.0, 0.0, 2.4, 0.0])
    for pull, f_moves in ((0.0, load_only), (1.0, False)):
        process = MassOnlyForce()
        dual = DualFilter(LAYOUT, process, LinearObservation(), 100, push_load_only=load_only)
        inputs = replace(make_inputs(), is_pull=torch.tensor(pull, dtype=DTYPE))
        generator, belief = torch.Generator().manual_seed(1), prior_belief()
        for _ in range(20):
            belief = dual.step(belief, inputs, DT_S, observation, generator)
        assert float(belief.mean[6]) > PRIOR_MEAN[6] + 0.1
        assert bool(belief.mean[7] > PRIOR_MEAN[7] + 0.15) is f_moves
        if not f_moves:
            assert abs(float(belief.mean[7]) - PRIOR_MEAN[7]) < 0.05


class ContactGatedObservation(LinearObservation):
    """Marks both forces unexplained while the measured one is under 0.3 N (no contact)."""

    def unexplained(
        self, observation: Tensor, expected: Tensor, tcp_xy_m: Tensor | None
    ) -> Tensor:
        mask = torch.zeros(observation.shape, dtype=torch.bool)
        mask[..., 3:] = observation[..., 3:].norm(dim=-1, keepdim=True) < 0.3
        return mask


def test_unexplained_forces_leave_the_parameters_alone() -> None:
    """A measured 0 N (before contact) against a model whose force is 2 m pulls m down; the
    same step with the forces unexplained leaves m where it was."""
    observation = as_tensor([0.0, 0.0, 0.0, 0.0, 0.0])
    for observation_model, falls in ((LinearObservation(), True),
                                     (ContactGatedObservation(), False)):  # fmt: skip
        dual = DualFilter(LAYOUT, MassOnlyForce(), observation_model, 100)
        generator, belief = torch.Generator().manual_seed(1), prior_belief()
        for _ in range(20):
            belief = dual.step(belief, make_inputs(), DT_S, observation, generator)
        assert bool(float(belief.mean[6]) < PRIOR_MEAN[6] - 0.1) is falls
        if not falls:
            assert abs(float(belief.mean[6]) - PRIOR_MEAN[6]) < 0.05


def test_projection_lands_on_the_feasible_set() -> None:
    layout = StateLayout(2)
    generator = torch.Generator().manual_seed(2)
    states = torch.randn(4, 50, layout.size, generator=generator, dtype=DTYPE) * 0.2
    link_size_m = torch.tensor([[0.1, 0.05], [0.2, 0.1]], dtype=DTYPE).expand(4, 2, 2)
    projected = project_feasible(states, layout, link_size_m)
    assert feasible(projected, layout, link_size_m).all()
    assert not feasible(states, layout, link_size_m).all()
    is_feasible = feasible(states, layout, link_size_m)
    assert torch.equal(projected[is_feasible], states[is_feasible])


def test_a_negative_mean_takes_the_moments_of_the_gaussian_truncated_at_zero() -> None:
    from scipy.stats import truncnorm

    mean = as_tensor([-1.0, 3.0, -2.0, 0.4])
    cov = as_tensor([[1.0, 0.5, 0.0, 0.1], [0.5, 2.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0],
                     [0.1, 0.0, 0.0, 0.5]])  # fmt: skip
    new_mean, new_cov = truncate_negative_means(mean, cov, rows=(0, 3))
    # x0 ~ N(-1, 1) given x0 > 0; x1 moves by its regression 0.5 on x0 (exact for a Gaussian).
    x0_mean, x0_var = truncnorm.stats(1.0, np.inf, loc=-1.0, scale=1.0, moments="mv")
    assert float(new_mean[0]) == pytest.approx(x0_mean, rel=1e-9)
    assert float(new_cov[0, 0]) == pytest.approx(x0_var, rel=1e-9)
    assert float(new_mean[1]) == pytest.approx(3.0 + 0.5 * (x0_mean + 1.0), rel=1e-9)
    assert float(new_cov[1, 1]) == pytest.approx(2.0 - 0.25 + 0.25 * x0_var, rel=1e-9)
    assert float(new_cov[0, 1]) == pytest.approx(0.5 * x0_var, rel=1e-9)
    # Row 2 is not bounded; row 3's mean is positive: neither is truncated.
    assert float(new_mean[2]) == -2.0 and new_cov[2, 2] == 1.0
    assert float(new_mean[3]) == pytest.approx(0.4 + 0.1 * (x0_mean + 1.0), rel=1e-9)
    assert_spd(new_cov)
    unchanged = truncate_negative_means(mean.abs(), cov, rows=(0, 1, 3))
    assert torch.equal(unchanged[0], mean.abs()) and torch.equal(unchanged[1], cov)


def test_a_mass_the_forces_call_for_below_zero_keeps_a_positive_mean() -> None:
    """The model sees every point with m <= 0 at the floor, so forces only a massless object
    could give favour all of them alike: their raw values would pull the mean below zero."""
    assert StateLayout(2).bounded_below == (0, 1, 4, 5, 8)
    names = StateLayout(2).names[12:]
    assert [names[row] for row in StateLayout(2).bounded_below] == [
        "m_0", "f_0", "m_1", "f_1", "f_j_0"]  # fmt: skip
    dual = toy_filter(sigma_points=400)
    mean = as_tensor(PRIOR_MEAN.copy())
    mean[6] = 0.05
    belief, inputs = Belief(mean, torch.diag(as_tensor(PRIOR_VAR))), make_inputs()
    generator = torch.Generator().manual_seed(3)
    for _ in range(5):
        observation = torch.cat([belief.mean[:3], as_tensor([-0.3, 1.2])])
        belief = dual.step(belief, inputs, DT_S, observation, generator)
    assert 0.0 < float(belief.mean[6]) < 0.05
    assert_spd(belief.cov)


def assert_spd(cov: Tensor) -> None:
    assert torch.equal(cov, cov.mT)
    assert int(torch.linalg.cholesky_ex(cov).info) == 0
    assert torch.linalg.eigvalsh(cov).min() > 0


@pytest.mark.parametrize("textbook", [True, False])
def test_covariance_stays_spd_for_1000_steps(textbook: bool) -> None:
    """Both the textbook filter and the one the skills use; the latter also ends near the
    truth and within 3 std of it (the textbook one's weights degenerate: it ends wherever its
    points collapsed)."""
    system = joint_system()
    observations = simulate(system, steps=1000, seed=4)
    dual = toy_filter(100) if textbook else DualFilter(LAYOUT, LinearProcess(), LinearObservation())
    generator = torch.Generator().manual_seed(12)
    belief, inputs = prior_belief(), make_inputs()
    for z in observations:
        belief = dual.step(belief, inputs, DT_S, as_tensor(z), generator)
        assert_spd(belief.cov)
    if not textbook:
        error = belief.mean[6:8] - as_tensor(TRUE_PARAMETERS[:2])
        assert bool((error.abs() < 0.05).all()), error
        z_score = error / belief.cov.diagonal()[6:8].sqrt()
        assert bool((z_score.abs() < 3).all()), z_score


def batch_inputs(count: int) -> ProcessInput:
    inputs = make_inputs((count,))
    sizes = torch.tensor([0.5, 0.3, 0.2], dtype=DTYPE)[:count]
    return replace(inputs, link_size_m=sizes[:, None, None].expand(count, 1, 2))


def test_batch_equals_separate_runs() -> None:
    generator = torch.Generator().manual_seed(6)
    dual = toy_filter(sigma_points=200)
    observations = as_tensor(simulate(joint_system(), steps=3, seed=7))
    shifts = torch.tensor([0.0, 0.1, -0.2], dtype=DTYPE)
    batched = Belief(prior_belief().mean + shifts[:, None], prior_belief().cov.expand(3, 10, 10))
    separate = [Belief(batched.mean[b], batched.cov[b]) for b in range(3)]
    inputs = batch_inputs(3)
    for z in observations:
        state_noise = torch.randn(3, 200, 10, generator=generator, dtype=DTYPE)
        process_noise = torch.randn(3, 200, 6, generator=generator, dtype=DTYPE)
        batched = dual.update(
            *dual.propagate(batched, inputs, DT_S, state_noise, process_noise),
            z + shifts[:, None],
        )
        for b in range(3):
            one_inputs = replace(inputs, link_size_m=inputs.link_size_m[b])
            predicted = dual.propagate(
                separate[b], one_inputs, DT_S, state_noise[b], process_noise[b]
            )
            separate[b] = dual.update(*predicted, z + shifts[b])
    for b in range(3):
        torch.testing.assert_close(batched.mean[b], separate[b].mean, rtol=0, atol=1e-12)
        torch.testing.assert_close(batched.cov[b], separate[b].cov, rtol=0, atol=1e-12)



def test_draws_for_one_belief_serve_a_batch_as_if_repeated() -> None:
    """A batch of beliefs predicted with one set of draws [C, n] (made antithetic once) is
    what ``propagate`` gives with those draws repeated for every element."""
    generator = torch.Generator().manual_seed(8)
    dual = toy_filter(sigma_points=40)
    shifts = torch.tensor([0.0, 0.1, -0.2], dtype=DTYPE)
    beliefs = Belief(prior_belief().mean + shifts[:, None], prior_belief().cov.expand(3, 10, 10))
    state_noise = torch.randn(40, 10, generator=generator, dtype=DTYPE)
    process_noise = torch.randn(40, 6, generator=generator, dtype=DTYPE)
    inputs = batch_inputs(3)
    alike, sigma_alike, _ = dual.propagate(beliefs, inputs, DT_S, state_noise, process_noise)
    repeated = (state_noise.expand(3, -1, -1), process_noise.expand(3, -1, -1))
    want, sigma_want, _ = dual.propagate(beliefs, inputs, DT_S, *repeated)
    torch.testing.assert_close(sigma_alike, sigma_want, rtol=0, atol=1e-12)
    torch.testing.assert_close(alike.mean, want.mean, rtol=0, atol=1e-12)
    torch.testing.assert_close(alike.cov, want.cov, rtol=0, atol=1e-12)
    assert not torch.allclose(alike.mean[0], alike.mean[1])  # the elements do differ
    with pytest.raises(ValueError, match="same leading dimensions"):
        dual.propagate(beliefs, inputs, DT_S, state_noise, process_noise.expand(3, -1, -1))

def test_gradients_flow_from_the_posterior_to_a_model_parameter() -> None:
    accel_gain = as_tensor(ACCEL_GAIN).requires_grad_(True)
    dual = toy_filter(sigma_points=100, process=LinearProcess(accel_gain))
    generator = torch.Generator().manual_seed(8)
    observations = as_tensor(simulate(joint_system(), steps=5, seed=9))
    belief, inputs = prior_belief(), batch_inputs(2)
    belief = Belief(belief.mean.expand(2, 10), belief.cov.expand(2, 10, 10))
    for z in observations:
        belief = dual.step(belief, inputs, DT_S, z.expand(2, 5), generator)
    (belief.mean.sum() + belief.cov.diagonal(dim1=-2, dim2=-1).sum()).backward()
    assert accel_gain.grad is not None
    assert torch.isfinite(accel_gain.grad).all()
    assert accel_gain.grad.abs().max() > 0


def test_cholesky_safe_handles_a_singular_covariance() -> None:
    vector = torch.tensor([[1.0, 2.0, 3.0]], dtype=DTYPE)
    factor = cholesky_safe(vector.T @ vector)
    assert torch.isfinite(factor).all()
    torch.testing.assert_close(factor @ factor.T, vector.T @ vector, rtol=0, atol=1e-9)


class NanProcess(LinearProcess):
    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        prediction = super().predict(states, inputs, dt_s)
        pose = prediction.pose.clone()
        pose[..., 7, 4] = float("nan")
        return replace(prediction, pose=pose)


class NanObservation(LinearObservation):
    def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
        expected = super().expected(states, force_n).clone()
        expected[..., 3, 1] = float("inf")
        return expected


def test_nan_raises_a_data_error_naming_the_entry() -> None:
    generator = torch.Generator().manual_seed(10)
    observation = as_tensor([0.0, 0.0, 0.0, 1.0, 1.0])
    bad_observation = observation.clone()
    bad_observation[2] = float("nan")
    with pytest.raises(DataError, match=r"observation\[2\]"):
        toy_filter(10).step(prior_belief(), make_inputs(), DT_S, bad_observation, generator)
    with pytest.raises(DataError, match=r"prediction\.pose\[vy_0\]"):
        dual = toy_filter(10, NanProcess())
        dual.step(prior_belief(), make_inputs(), DT_S, observation, generator)
    with pytest.raises(DataError, match=r"expected observation\[1\] = inf at leading index \(3,\)"):
        dual = DualFilter(LAYOUT, LinearProcess(), NanObservation(), 10)
        dual.step(prior_belief(), make_inputs(), DT_S, observation, generator)
    mean = prior_belief().mean.clone()
    mean[6] = float("nan")
    with pytest.raises(DataError, match=r"m_0"):
        toy_filter(10).step(
            Belief(mean, prior_belief().cov), make_inputs(), DT_S, observation, generator
        )


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ({(2, 1): math.nan}, r"v\[b\] = nan at leading index \(2,\)"),
        ({(2, 1): math.inf}, r"v\[b\] = inf at leading index \(2,\)"),
        ({(0, 0): -math.inf, (2, 1): math.inf}, r"v\[a\] = -inf at leading index \(0,\)"),
    ],
)
def test_require_finite_names_the_first_bad_entry(bad: dict, message: str) -> None:
    """A NaN, an inf, or an inf and a -inf that cancel into a NaN in a sum: the first is
    named by entry and leading index."""
    values = torch.ones(3, 2, dtype=DTYPE)
    for index, value in bad.items():
        values[index] = value
    with pytest.raises(DataError, match=message):
        require_finite(values, "v", ("a", "b"))


def test_require_finite_passes_finite_values_whose_sum_overflows() -> None:
    require_finite(torch.zeros(0, dtype=DTYPE), "empty")
    require_finite(torch.full((3, 2), 1e308, dtype=DTYPE), "large")


class TableAndNan(LinearObservation):
    """100 entries the same for every point (the table's pixels), then (x, y, theta, fx, fy)
    with a NaN at entry 101 (y) of point 3."""

    def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
        table = torch.full((*states.shape[:-1], 100), 0.5, dtype=DTYPE)
        expected = torch.cat([table, super().expected(states, force_n)], -1)
        expected[..., 3, 101] = float("nan")
        return expected

    def noise_var(self, observation: Tensor) -> Tensor:
        return torch.full(observation.shape, 1e-3, dtype=DTYPE)


@pytest.mark.parametrize("marginal", [True, False])
def test_a_bad_entry_is_named_by_its_place_in_the_whole_observation(marginal: bool) -> None:
    """Only the entries where the points differ are compared point by point; the error still
    names the entry's index in the full observation."""
    observation = torch.cat([torch.full((100,), 0.5, dtype=DTYPE), as_tensor([0, 0, 0, 1, 1])])
    dual = DualFilter(LAYOUT, LinearProcess(), TableAndNan(), 10,
                      marginal_parameter_likelihood=marginal)  # fmt: skip
    generator = torch.Generator().manual_seed(10)
    with pytest.raises(DataError, match=r"expected observation\[101\] = nan at leading index"):
        dual.step(prior_belief(), make_inputs(), DT_S, observation, generator)


class ExplodingObservation(LinearObservation):
    """Expected observations so spread that the unscented update is numerically singular."""

    def expected(self, states: Tensor, force_n: Tensor) -> Tensor:
        return super().expected(states, force_n) * 1e10


def test_a_diverged_pose_update_raises_a_data_error_naming_the_widest_entry() -> None:
    generator = torch.Generator().manual_seed(11)
    observation = as_tensor([0.0, 0.0, 0.0, 1.0, 1.0])
    dual = DualFilter(LAYOUT, LinearProcess(), ExplodingObservation(), 10)
    with pytest.raises(
        DataError, match=r"numerically singular.*diverged \(widest pose entry \w+_0"
    ):
        dual.step(prior_belief(), make_inputs(), DT_S, observation, generator)


def test_invalid_settings_are_rejected() -> None:
    with pytest.raises(ValueError, match="liu_west_delta"):
        DualFilter(LAYOUT, LinearProcess(), LinearObservation(), liu_west_delta=0.2)
    with pytest.raises(ValueError, match="ukf_kappa"):
        DualFilter(LAYOUT, LinearProcess(), LinearObservation(), ukf_kappa=-3.0)
    with pytest.raises(ValueError, match="evidence_scale"):
        DualFilter(LAYOUT, LinearProcess(), LinearObservation(), evidence_scale=0.0)
    with pytest.raises(ValueError, match="twist_bound"):
        DualFilter(LAYOUT, LinearProcess(), LinearObservation(), twist_bound=(0.0, 1.0))


def test_bound_twist_scales_the_speed_and_clips_the_rate() -> None:
    pose = as_tensor([1.0, 2.0, 3.0, 0.3, 0.4, -5.0, 1.0, 2.0, 3.0, 0.03, 0.04, 0.5])
    bounded = bound_twist(pose, 0.25, 2.0)
    expected = [1.0, 2.0, 3.0, 0.15, 0.2, -2.0, 1.0, 2.0, 3.0, 0.03, 0.04, 0.5]
    torch.testing.assert_close(bounded, as_tensor(expected))


class RunawayProcess(LinearProcess):
    """Doubles every velocity each step, which the positions do not show: a learned model
    fed its own extrapolation, with the camera seeing positions only."""

    def predict(self, states: Tensor, inputs: ProcessInput, dt_s: float) -> Prediction:
        prediction = super().predict(states, inputs, dt_s)
        pose = torch.cat([states[..., :3], 2.0 * states[..., 3:6] + 0.1], -1)
        return Prediction(pose, prediction.force_n, prediction.process_var)


def test_a_twist_bound_keeps_a_runaway_model_physical() -> None:
    generator = torch.Generator().manual_seed(12)
    observation = as_tensor([0.0, 0.0, 0.0, 1.0, 1.0])
    beliefs = {}
    for bound in (None, (0.25, 2.0)):
        dual = DualFilter(LAYOUT, RunawayProcess(), LinearObservation(), 50, twist_bound=bound)
        belief = prior_belief()
        for _ in range(20):
            belief = dual.step(belief, make_inputs(), DT_S, observation, generator)
        beliefs[bound] = belief.mean
    assert float(beliefs[None][3:5].norm()) > 1e4  # unbounded, the velocity runs away
    assert float(beliefs[(0.25, 2.0)][3:5].norm()) <= 0.25 + 1e-9
    assert abs(float(beliefs[(0.25, 2.0)][5])) <= 2.0 + 1e-9


def test_a_smaller_evidence_scale_learns_the_parameters_more_slowly() -> None:
    """A power likelihood: with 1/10 of the evidence per step the parameter variance after 30
    steps lies between the full-evidence posterior's and the prior's."""
    system = joint_system()
    observations = simulate(system, 30, seed=2)

    def parameter_var(scale: float) -> Tensor:
        dual = DualFilter(LAYOUT, LinearProcess(), LinearObservation(), 200, evidence_scale=scale)
        generator, belief = torch.Generator().manual_seed(0), prior_belief()
        for observation in observations:
            belief = dual.step(belief, make_inputs(), DT_S, as_tensor(observation), generator)
        return belief.cov.diagonal()[6:]

    full, tenth, prior = parameter_var(1.0), parameter_var(0.1), prior_belief().cov.diagonal()[6:]
    assert bool((full < tenth).all() and (tenth < prior).all())


def test_tempering_keeps_the_effective_sample_size() -> None:
    from vistac.plugins.filters.dual import effective_sample_size, temper_log_weights

    log_likelihood = -0.5 * torch.linspace(0.0, 400.0, 100, dtype=DTYPE)[None].repeat(2, 1)
    log_likelihood[1] = 0.0  # already uniform: untouched
    log_weights, beta = temper_log_weights(log_likelihood, 50.0)
    ess = effective_sample_size(log_weights)
    assert 49.0 < float(ess[0]) < 51.0 and float(beta[0]) < 1.0
    assert float(beta[1]) == 1.0
    torch.testing.assert_close(log_weights.exp().sum(-1), torch.ones(2, dtype=DTYPE))


def test_pose_floor_widens_the_unscented_spread_only() -> None:
    """A pose std below the floor is raised to it before the unscented update: with a linear
    observation of (x, y, theta) the update is the Kalman one from the floored variance, and
    the entries without a floor (the twist) keep theirs."""
    floor = (0.01, 0.02, 0.1, 0.0, 0.0, 0.0)
    dual = DualFilter(LAYOUT, LinearProcess(), LinearObservation(), 10, pose_std_floor=floor)
    assert dual.pose_var_floor is not None and dual.pose_var_floor.shape == (LAYOUT.n_pose,)
    variance = as_tensor([1e-8] * LAYOUT.n_pose + list(PRIOR_VAR[6:]))
    belief = Belief(as_tensor(PRIOR_MEAN), torch.diag(variance))
    observation = as_tensor([0.002, -0.001, 0.01, 0.0, 0.0])
    noise_var = LinearObservation().noise_var(observation)
    mean, cov, _ = dual._update_pose(
        belief, belief.mean[6:], torch.zeros(2, dtype=DTYPE), observation, noise_var
    )
    floored = torch.tensor(floor[:3], dtype=DTYPE).square()
    gain = floored / (floored + POSITION_VAR)
    torch.testing.assert_close(cov.diagonal()[:3], gain * POSITION_VAR)
    torch.testing.assert_close(mean[:3], gain * observation[:3])
    torch.testing.assert_close(cov.diagonal()[3:], variance[3:6])
    with pytest.raises(ValueError, match="pose_std_floor"):
        DualFilter(LAYOUT, LinearProcess(), LinearObservation(), pose_std_floor=(1.0,))
    with pytest.raises(ValueError, match="min_ess_fraction"):
        DualFilter(LAYOUT, LinearProcess(), LinearObservation(), min_ess_fraction=2.0)


# ---------------------------------------------------------------------------------------------
# Fast paths against the plain formulas


def halving_bisection(log_likelihood: Tensor, min_ess: float, iterations: int = 40) -> Tensor:
    """Reference tempering: beta halved one bit at a time, the ESS by log-sum-exp."""
    from vistac.plugins.filters.dual import effective_sample_size

    def ess(beta: Tensor) -> Tensor:
        scaled = beta.unsqueeze(-1) * log_likelihood
        return effective_sample_size(scaled - torch.logsumexp(scaled, -1, keepdim=True))

    ones = log_likelihood.new_ones(log_likelihood.shape[:-1])
    low, high = torch.zeros_like(ones), ones.clone()
    for _ in range(iterations):
        middle = 0.5 * (low + high)
        ok = ess(middle) >= min_ess
        low, high = torch.where(ok, middle, low), torch.where(ok, high, middle)
    return torch.where(ess(ones) >= min_ess, ones, low)


@pytest.mark.parametrize("seed", range(5))
def test_tempering_finds_the_beta_of_one_bit_bisection(seed: int) -> None:
    from vistac.plugins.filters.dual import temper_log_weights

    generator = torch.Generator().manual_seed(seed)
    spread = torch.tensor([[0.1], [3.0], [30.0], [3000.0]], dtype=DTYPE)
    log_likelihood = spread * torch.randn(4, 100, generator=generator, dtype=DTYPE)
    _, beta = temper_log_weights(log_likelihood, 80.0)
    torch.testing.assert_close(beta, halving_bisection(log_likelihood, 80.0), rtol=0, atol=2e-12)
    assert float(beta[0]) == 1.0 and float(beta[-1]) < 0.01


def residual_case(seed: int) -> tuple[Tensor, Tensor, Tensor]:
    """expected [2, 30, 50], observation [2, 50], noise_var [2, 50]: depth-like values with
    entries where every point agrees (zero spread)."""
    generator = torch.Generator().manual_seed(seed)
    expected = 0.5 + 0.05 * torch.randn(2, 30, 50, generator=generator, dtype=DTYPE)
    expected[..., :10] = 0.7
    observation = 0.5 + 0.05 * torch.randn(2, 50, generator=generator, dtype=DTYPE)
    noise_var = 1e-4 * (1.0 + torch.rand(2, 50, generator=generator, dtype=DTYPE))
    return expected, observation, noise_var


def test_likelihoods_from_squared_residuals_equal_the_plain_formulas() -> None:
    from vistac.plugins.filters.dual import (
        modality_log_likelihoods,
        observation_log_likelihood,
    )

    expected, observation, noise_var = residual_case(0)
    scaled = (expected - observation.unsqueeze(-2)).square() / noise_var.unsqueeze(-2)
    torch.testing.assert_close(
        observation_log_likelihood(expected, observation, noise_var), -0.5 * scaled.sum(-1)
    )
    visual, tactile = scaled[..., :-2].mean(-1), scaled[..., -2:].mean(-1)
    plain = [torch.logsumexp(-0.5 * part, -1) - math.log(30) for part in (visual, tactile)]
    torch.testing.assert_close(
        modality_log_likelihoods(expected, observation, noise_var, 2), torch.stack(plain, -1)
    )


def test_marginal_likelihood_equals_the_plain_fit_and_residual_formulas() -> None:
    """Expected observations = linear in the parameters + a scatter orthogonal to them: the
    fast marginal likelihood equals N(z; linear part, R + scatter variance (C - p - 1 dof))
    written out, and a degenerate parameter block stays finite."""
    generator = torch.Generator().manual_seed(4)
    parameters = torch.randn(2, 30, 4, generator=generator, dtype=DTYPE)
    linear = 0.5 + parameters @ torch.randn(4, 50, generator=generator, dtype=DTYPE)
    design = torch.cat([torch.ones(2, 30, 1, dtype=DTYPE), parameters], -1)
    scatter = torch.randn(2, 30, 50, generator=generator, dtype=DTYPE)
    scatter -= design @ torch.linalg.lstsq(design, scatter).solution  # orthogonal to the design
    expected = linear + scatter
    observation = 0.5 + torch.randn(2, 50, generator=generator, dtype=DTYPE)
    noise_var = 0.1 + torch.rand(2, 50, generator=generator, dtype=DTYPE)
    variance = noise_var + scatter.square().sum(-2) / 25
    plain = -0.5 * ((linear - observation.unsqueeze(-2)).square() / variance.unsqueeze(-2)).sum(-1)
    mean_residual = expected.mean(-2) - observation
    centred_sums = 30 * expected.var(-2, correction=0)

    def likelihood(fit: ParameterFit, noisy: bool = False) -> Tensor:
        inverse_var = marginal_inverse_var(fit, centred_sums, noise_var)
        projection = (expected @ (inverse_var * mean_residual).unsqueeze(-1))[..., 0]
        fit_noise = iid_fit_noise(fit, inverse_var, noise_var, projection) if noisy else None
        return marginal_log_likelihood(fit, mean_residual, inverse_var, fit_noise)

    fit = parameter_fit(parameters, expected)
    plain_fast = likelihood(fit)
    torch.testing.assert_close(plain_fast, plain, rtol=1e-6, atol=1e-6)  # (the ridge)
    # A signal far above the fit's noise: taking the noise out changes the weights little.
    spread = plain - plain.mean(-1, keepdim=True)
    debiased = likelihood(fit, noisy=True)
    error = debiased - debiased.mean(-1, keepdim=True) - spread
    assert float(error.abs().max()) < 0.1 * float(spread.abs().max())
    same = parameters[..., :1].expand(2, 30, 4)
    degenerate = likelihood(parameter_fit(same, expected), noisy=True)
    assert bool(torch.isfinite(degenerate).all())


def test_paired_fit_noise_sees_only_what_is_not_linear_in_the_draws() -> None:
    """Antithetic points whose expected observation is linear in the draws fit their slopes
    exactly (no noise, up to round-off); a non-linear part is noise, less than the
    independent-points bound says."""
    generator = torch.Generator().manual_seed(6)
    pairs = antithetic_noise(torch.randn(100, 12, generator=generator, dtype=DTYPE))
    gain = torch.randn(12, 300, generator=generator, dtype=DTYPE)
    parameters = pairs[:, 8:]  # the last 4 draws are the parameters' deviations
    noise_var = torch.full((300,), 0.01, dtype=DTYPE)
    weights = torch.randn(300, generator=generator, dtype=DTYPE)
    fits = []
    for expected in (pairs @ gain, pairs @ gain + torch.tanh(2.0 * pairs @ gain)):
        fit = parameter_fit(parameters, expected)
        inverse_var = marginal_inverse_var(fit, 100 * expected.var(-2, correction=0), noise_var)
        paired = paired_fit_noise(expected, pairs, inverse_var, weights)
        iid = iid_fit_noise(fit, inverse_var, noise_var, expected @ weights)
        assert paired is not None
        fits.append((paired, iid))
    (linear, linear_iid), (curved, curved_iid) = fits
    assert float(linear_iid.information) > 100  # the iid bound counts the draws' scatter
    # (float32 round-off)
    assert float(linear.information) < 1e-5 * float(linear_iid.information)
    assert float(linear.score) < 1e-5 * float(linear_iid.score)
    assert float(curved.information) > 1
    assert float(curved.information) < float(curved_iid.information)
    assert paired_fit_noise(pairs @ gain, pairs[:, :3].repeat(1, 20), inverse_var, weights) is None


def test_the_filter_the_skills_use_follows_the_kalman_filter_for_1000_steps() -> None:
    """Default settings (marginal likelihood, fit noise taken out, tempering) on the
    linear-Gaussian toy: the parameters end within 2 Kalman std of the Kalman mean with a std
    within a factor 2 of the Kalman one (the raw fit's noise made them 3.6 times too sure)."""
    system = joint_system()
    observations = simulate(system, steps=1000, seed=4)
    reference_mean, reference_cov = kalman_filter(system, observations)[-1]
    dual = DualFilter(LAYOUT, LinearProcess(), LinearObservation())
    generator = torch.Generator().manual_seed(12)
    belief, inputs = prior_belief(), make_inputs()
    for z in observations:
        belief = dual.step(belief, inputs, DT_S, as_tensor(z), generator)
    reference_std = as_tensor(np.sqrt(np.diag(reference_cov))[6:])
    std = belief.cov.diagonal()[6:].sqrt()
    assert bool((std / reference_std).min() > 0.5) and bool((std / reference_std).max() < 2.0)
    error = (belief.mean[6:] - as_tensor(reference_mean[6:])) / reference_std
    assert bool((error.abs() < 2.0).all()), error


def test_consumed_expected_observations_give_the_same_update() -> None:
    """Without autograd the filter writes the residuals over the expected observations; with
    autograd it keeps them: the same posterior either way."""
    dual = DualFilter(LAYOUT, LinearProcess(), LinearObservation(), 50)
    observation = as_tensor([0.01, -0.02, 0.03, 0.9, 1.1])
    posteriors = []
    for grad in (False, True):
        generator = torch.Generator().manual_seed(3)
        mean = as_tensor(PRIOR_MEAN).requires_grad_(grad)
        with torch.set_grad_enabled(grad):
            belief = Belief(mean, torch.diag(as_tensor(PRIOR_VAR)))
            posteriors.append(dual.step(belief, make_inputs(), DT_S, observation, generator))
    torch.testing.assert_close(posteriors[0].mean, posteriors[1].mean.detach())
    torch.testing.assert_close(posteriors[0].cov, posteriors[1].cov.detach())


def test_leaving_out_the_entries_no_point_varies_in_changes_nothing(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """A box seen from above in a 64 x 64 depth image plus two forces, the camera's noise on
    every pixel: the update compares the points only where their expected observations
    differ (a few hundred of 4098 entries), and its posterior and per-modality likelihoods
    equal those of the update over every entry."""
    from vistac.plugins.filters import dual as dual_module
    from vistac.plugins.filters.observation import (
        DepthProjector,
        ObsNoiseNet,
        ProjectionObservationModel,
        observation_vector,
    )
    from vistac.testing import build_components
    from vistac.types import CameraIntrinsics

    torch.manual_seed(0)
    axes = torch.linspace(-0.04, 0.04, 30), torch.linspace(-0.03, 0.03, 24)
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)
    points = torch.cat([grid.reshape(-1, 2), torch.full((720, 1), 0.05)], -1).to(DTYPE)
    camera = np.array([[1.0, 0, 0, 0], [0, -1.0, 0, 0], [0, 0, -1.0, 0.5], [0, 0, 0, 1.0]])
    projector = DepthProjector(
        points, torch.zeros(720, dtype=torch.int64), torch.zeros(1, 3, dtype=DTYPE),
        CameraIntrinsics(64, 64, 120.0, 120.0, 31.5, 31.5), camera,
    )  # fmt: skip
    model = ProjectionObservationModel(LAYOUT, projector, ObsNoiseNet())
    gnn = {"plugin": "filters.gnn", "with": {"hidden": 16}}
    process = build_components({"model": gnn}, tmp_path).component("model")
    dual = DualFilter(LAYOUT, process, model, 40, push_load_only=True)
    depth = projector.render(torch.tensor([[0.004, 0.0, 0.02]], dtype=DTYPE))
    depth = depth + 0.002 * torch.randn(depth.shape, dtype=DTYPE)
    observation = observation_vector(depth, torch.tensor([0.8, 0.1]), projector.background_m)
    mean = torch.zeros(LAYOUT.size, dtype=DTYPE)
    mean[6:] = torch.tensor([0.5, 0.3, 0.0, 0.0], dtype=DTYPE)
    std = torch.tensor([0.004, 0.004, 0.05, 0.01, 0.01, 0.1, 0.2, 0.1, 0.02, 0.02], dtype=DTYPE)
    belief = Belief(mean, torch.diag(std**2))
    inputs = replace(make_inputs(half_extent_m=0.04), tcp=torch.tensor(
        [-0.05, 0.0, 0.0, 0.02, 0.0, 0.0], dtype=DTYPE))  # fmt: skip

    def step() -> tuple[Belief, Tensor]:
        generator = torch.Generator().manual_seed(3)
        with torch.no_grad():
            posterior = dual.step(belief, inputs, DT_S, observation, generator)
        return posterior, dual.last_log_likelihood

    varying = dual_module.varying_columns
    counts: list[int] = []
    monkeypatch.setattr(dual_module, "varying_columns",
                        lambda e, n=0: counts.append(len(c := varying(e, n))) or c)  # fmt: skip
    fewer, fewer_likelihood = step()
    assert 0 < max(counts) < 1000, counts
    monkeypatch.setattr(dual_module, "varying_columns",
                        lambda e, n=0: torch.arange(e.shape[-1]))  # fmt: skip
    every, every_likelihood = step()
    torch.testing.assert_close(fewer.mean, every.mean, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(fewer.cov, every.cov, rtol=1e-7, atol=1e-14)
    torch.testing.assert_close(fewer_likelihood, every_likelihood, rtol=1e-9, atol=1e-9)
    assert not torch.equal(fewer.mean, belief.mean)


def test_at_rest_zeroes_every_links_twist_and_nothing_else() -> None:
    layout = StateLayout(2)
    states = torch.arange(2 * layout.size, dtype=DTYPE).reshape(2, layout.size) + 1.0
    rest = layout.at_rest(states)
    twist = [layout.index(f"{name}_{link}") for link in (0, 1) for name in ("vx", "vy", "omega")]
    assert bool((rest[:, twist] == 0).all())
    others = [i for i in range(layout.size) if i not in twist]
    assert torch.equal(rest[:, others], states[:, others])
