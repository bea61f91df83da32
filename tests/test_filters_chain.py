"""The analytical model of welded and hinged chains (vistac.plugins.filters.chain): the
one-link case against Lynch's closed form, the statics of every link and hinge of random
chains checked from first principles, and known motions of the model."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from simctx import TestContext
from torch import Tensor
from vistac.plugins.filters import chain
from vistac.plugins.filters.analytical import (
    characteristic_length_m,
    quasi_static_push,
)
from vistac.plugins.filters.models import AnalyticalProcessModel
from vistac.plugins.filters.nets import perp, rotate
from vistac.plugins.filters.state import DTYPE, ProcessInput, StateLayout

SPEED_MPS = 0.025
DT_S = 0.05


def close(value: Tensor, expected: Tensor | float, atol: float) -> None:
    """value equals expected within atol (no relative tolerance)."""
    expected = torch.as_tensor(expected, dtype=DTYPE).expand_as(value)
    torch.testing.assert_close(value, expected, rtol=0, atol=atol)


def _cross(a: Tensor, b: Tensor) -> Tensor:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _links(
    com: Tensor, joints: Tensor, c: Tensor, f_max: Tensor, tau: Tensor
) -> chain.ChainProblem:
    twist_map = chain.chain_twist_map(com, joints)
    none = torch.zeros(*com.shape[:-2], 3, twist_map.shape[-1], dtype=DTYPE)
    return chain.ChainProblem(twist_map, c, f_max, tau, none, none[..., 0], none[..., 0].bool())


def test_one_link_is_lynchs_closed_form() -> None:
    """Sticking and slipping pushes of one link: the minimum-power motion equals
    ``quasi_static_push``'s to 1e-6 of the natural scales."""
    rng = np.random.default_rng(3)
    count = 80
    half = torch.tensor(rng.uniform(0.03, 0.07, (count, 2)))
    com = torch.tensor(rng.uniform(-0.3, 0.3, (count, 2))) * half
    across = torch.tensor(rng.uniform(-0.95, 0.95, count))
    contact = torch.stack([-half[:, 0], across * half[:, 1]], -1)
    angle = torch.tensor(rng.uniform(-1.3, 1.3, count))
    velocity = SPEED_MPS * torch.stack([torch.cos(angle), torch.sin(angle)], -1)
    normal = torch.tensor([[1.0, 0.0]], dtype=DTYPE).expand(count, 2)
    f_max = torch.tensor(rng.uniform(0.5, 5.0, count))
    mu = 0.4
    c = characteristic_length_m(half, com)
    expected = quasi_static_push(contact - com, normal, velocity, f_max, c, mu)
    links = _links(com[:, None], torch.zeros(count, 0, 2, dtype=DTYPE), c[:, None],
                   f_max[:, None], torch.zeros(count, 0, dtype=DTYPE))  # fmt: skip
    rows = chain.point_velocity_rows(links.twist_map[:, 0], com, contact)
    motion = chain.push_motion(links, rows, normal, velocity, mu)
    z = motion.z
    assert 10 < int(expected.sticking.sum()) < count - 10, "both sticking and slipping covered"
    # Relative to the natural scales: pusher speed, speed / c, f_max.
    close(z[:, :2] / SPEED_MPS, expected.velocity_mps / SPEED_MPS, 1e-6)
    close(z[:, 2] * c / SPEED_MPS, expected.omega_radps * c / SPEED_MPS, 1e-6)
    force = motion.wrench[:, 0, :2]
    # The smoothed norm (eta 1e-3 of the motion) lowers the force by about eta² / 2.
    close(force / f_max[:, None], expected.force_n / f_max[:, None], 1e-5)


def random_chains(count: int, n_links: int, seed: int) -> dict[str, Tensor]:
    """Chains of boxes along +x (each turned a little), pushed on a random link's side."""
    rng = np.random.default_rng(seed)
    half = torch.tensor(rng.uniform(0.03, 0.06, (count, n_links, 2)))
    theta = torch.tensor(rng.uniform(-0.4, 0.4, (count, n_links)))
    centres = [torch.zeros(count, 2, dtype=DTYPE)]
    joints = []
    for k in range(n_links - 1):
        side = torch.stack([half[:, k, 0], torch.zeros(count)], -1)
        joint = centres[k] + rotate(side, theta[:, k])
        joints.append(joint)
        arm = torch.stack([half[:, k + 1, 0], torch.zeros(count)], -1)
        centres.append(joint + rotate(arm, theta[:, k + 1]))
    centre = torch.stack(centres, 1)
    com_link = torch.tensor(rng.uniform(-0.3, 0.3, (count, n_links, 2))) * half
    com = centre + rotate(com_link, theta)
    link = torch.tensor(rng.integers(0, n_links, count))
    along = torch.tensor(rng.uniform(-0.9, 0.9, count))
    pick = torch.arange(count)
    local = torch.stack([along * half[pick, link, 0], -half[pick, link, 1]], -1)  # -y side
    contact = centre[pick, link] + rotate(local, theta[pick, link])
    normal = rotate(torch.tensor([[0.0, 1.0]], dtype=DTYPE).expand(count, 2), theta[pick, link])
    beta = torch.tensor(rng.uniform(-1.0, 1.0, count))
    velocity = SPEED_MPS * rotate(normal, beta)
    return {
        "com": com,
        "joints": torch.stack(joints, 1) if joints else torch.zeros(count, 0, 2, dtype=DTYPE),
        "c": characteristic_length_m(half, com_link),
        "f_max": torch.tensor(rng.uniform(0.5, 5.0, (count, n_links))),
        "tau": torch.tensor(rng.uniform(0.0, 0.25, (count, n_links - 1))),
        "link": link,
        "contact": contact,
        "normal": normal,
        "velocity": velocity,
    }


@pytest.mark.parametrize("n_links", [2, 3])
def test_random_chains_obey_statics(n_links: int) -> None:
    """First principles, not the solver's own conditions: every hinge moves with both its
    links; the pushed point moves with the pusher (sticking) or at its normal speed (slipping,
    the force then on the friction-cone edge, along the slip); each link's friction lies on
    its limit surface, or inside it for a link at rest; the friction's moments about the
    contact cancel (the pusher's force has none there); and each hinge holds the friction
    torque of the links beyond it (away from the pusher) up to its own friction, which it
    exerts exactly, against the turning, when it turns."""
    count, mu = 150, 0.4
    case = random_chains(count, n_links, seed=n_links)
    links = _links(case["com"], case["joints"], case["c"], case["f_max"], case["tau"])
    pick = torch.arange(count)
    rows = chain.point_velocity_rows(
        links.twist_map[pick, case["link"]], case["com"][pick, case["link"]], case["contact"]
    )
    motion = chain.push_motion(links, rows, case["normal"], case["velocity"], mu)
    twist = chain.link_twists(links, motion.z)  # [count, L, 3]
    com, force, moment = case["com"], motion.wrench[..., :2], motion.wrench[..., 2]

    def point_velocity(link: Tensor, point: Tensor) -> Tensor:
        link_twist = twist[pick, link]
        return link_twist[:, :2] + link_twist[:, 2:] * perp(point - com[pick, link])

    for k in range(n_links - 1):
        joint = case["joints"][:, k]
        near, far = torch.full((count,), k), torch.full((count,), k + 1)
        close((point_velocity(near, joint) - point_velocity(far, joint)) / SPEED_MPS, 0.0, 1e-6)
    scaled = torch.cat([twist[..., :2], case["c"].unsqueeze(-1) * twist[..., 2:]], -1)
    speed = scaled.norm(dim=-1)
    on_surface = (force**2).sum(-1) + (moment / case["c"]) ** 2
    moving = speed > 0.1 * SPEED_MPS  # well above the smoothing (eta 1e-3 of the motion)
    close(on_surface[moving].sqrt() / case["f_max"][moving], 1.0, 1e-4)
    assert (on_surface.sqrt() <= case["f_max"] * (1 + 1e-9)).all()
    assert (~moving).any(), "some links rest"

    pusher = force.sum(-2)
    tangent = perp(case["normal"])
    normal_force, tangent_force = (pusher * case["normal"]).sum(-1), (pusher * tangent).sum(-1)
    slip = case["velocity"] - point_velocity(case["link"], case["contact"])
    close((slip * case["normal"]).sum(-1) / SPEED_MPS, 0.0, 1e-6)
    slip_speed = (slip * tangent).sum(-1)
    sliding = slip_speed.abs() > 1e-6 * SPEED_MPS
    assert 10 < int(sliding.sum()) < count - 10, "both sticking and slipping covered"
    assert (normal_force > 0).all()
    assert (tangent_force[~sliding].abs() <= mu * normal_force[~sliding] * (1 + 1e-6)).all()
    edge = mu * normal_force[sliding] * torch.sign(slip_speed[sliding])
    close(tangent_force[sliding] - edge, 0.0, 1e-5)

    arm = com - case["contact"][:, None]
    close((_cross(arm, force) + moment).sum(-1), 0.0, 1e-5)
    turned = 0
    for k in range(n_links - 1):
        joint = case["joints"][:, k]
        beyond = torch.arange(n_links)[None] > k
        beyond = torch.where((case["link"] > k)[:, None], ~beyond, beyond)  # away from the pusher
        hinge_torque = ((_cross(com - joint[:, None], force) + moment) * beyond).sum(-1)
        rate = twist[:, k + 1, 2] - twist[:, k, 2]
        rate = torch.where(case["link"] > k, -rate, rate)  # the far side's turning
        tau = case["tau"][:, k]
        assert (hinge_torque.abs() <= tau + 1e-6).all()
        turning = rate.abs() > 0.5 * SPEED_MPS  # rad/s, well above the smoothing (1e-3 / 5 cm)
        turned += int(turning.sum())
        exerted = hinge_torque[turning] + tau[turning] * torch.sign(rate[turning])
        close(exerted / tau[turning], 0.0, 1e-3)
    assert turned > 10, "some hinges turn"


def _push_problems(n_links: int, seed: int) -> list[chain.ChainProblem]:
    """The minimum-power problems (sticking, then the friction cone's edges) that
    ``push_motion`` solves for 150 random chains."""
    case = random_chains(150, n_links, seed)
    links = _links(case["com"], case["joints"], case["c"], case["f_max"], case["tau"])
    pick = torch.arange(150)
    rows = chain.point_velocity_rows(
        links.twist_map[pick, case["link"]], case["com"][pick, case["link"]], case["contact"]
    )
    problems: list[chain.ChainProblem] = []
    solve = chain.solve_chain

    def recorded(problem: chain.ChainProblem, eta: float = chain.SMOOTHING) -> Tensor:
        problems.append(problem)
        return solve(problem, eta)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(chain, "solve_chain", recorded)
        chain.push_motion(links, rows, case["normal"], case["velocity"], 0.4)
    return problems


@pytest.mark.parametrize("n_links", [2, 3])
def test_newton_stops_when_every_point_is_solved(
    n_links: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each point stops at its own convergence: the sticking batch ends before NEWTON_STEPS
    iterations, the minima are those of running every point to NEWTON_STEPS (to 1e-7 of the
    unit-speed motion), and a point solved alone gives what it gives in its batch."""
    calls = [0]
    gradient_hessian = chain._gradient_hessian

    def counted(*args: object) -> tuple[Tensor, Tensor]:
        calls[0] += 1
        return gradient_hessian(*args)  # type: ignore[arg-type]

    problems, iterations = _push_problems(n_links, seed=10 + n_links), []
    monkeypatch.setattr(chain, "_gradient_hessian", counted)
    for problem in problems:
        calls[0] = 0
        z = chain.solve_chain(problem)
        iterations.append(calls[0])
        with monkeypatch.context() as patch:  # every point to the end: only a stay stops it
            patch.setattr(chain, "NEWTON_TOLERANCE", -1.0)
            close(z, chain.solve_chain(problem), 1e-7)
        points, _ = chain._points(problem)
        for k in (0, 7, 149):
            alone = chain.solve_chain(chain._take(points, torch.tensor([k])))
            close(alone[0], z.reshape(-1, z.shape[-1])[k], 1e-12)
    assert iterations[0] < chain.NEWTON_STEPS, "the sticking batch stops before the cap"


@pytest.mark.parametrize("n_links", [2, 3])
def test_the_line_search_weighs_the_power_of_each_trial(n_links: int) -> None:
    """The line search's powers, worked out from z and the step once, are those of ``power``
    at each trial point z + f step, with and without a grasp that lets a link turn."""
    generator = torch.Generator().manual_seed(n_links)
    for problem in _push_problems(n_links, seed=20 + n_links):
        points, _ = chain._points(problem)
        count, n = points.rows.shape[0], points.rows.shape[-1]
        grasped = points._replace(
            grasp_row=torch.randn(count, n, dtype=DTYPE, generator=generator),
            grasp_rate=torch.randn(count, dtype=DTYPE, generator=generator),
            grasp_friction_nm=torch.rand(count, dtype=DTYPE, generator=generator),
        )
        z, step = torch.randn(2, count, n, dtype=DTYPE, generator=generator)
        fractions = torch.tensor(chain.STEP_SIZES, dtype=DTYPE)
        trials = z + fractions.reshape(-1, 1, 1) * step
        for case in (points, grasped):
            along = chain._powers_along(case, z, step, fractions, chain.SMOOTHING)
            torch.testing.assert_close(along, chain.power(case, trials), rtol=1e-12, atol=0)


def chain_scenario(
    tau_nm: float, pd_rad: float = 0.0, is_pull: float = 0.0, second_theta: float = 0.0
) -> tuple[Tensor, ProcessInput]:
    """Two 90 mm squares side by side along +x (m 0.8 kg, f 0.3, CoMs at the centres), the
    gripper at link 0's -x side moving along pd_rad."""
    half = 0.045
    layout = StateLayout(2)
    states = torch.zeros(1, layout.size, dtype=DTYPE)
    states[0, 6] = 2 * half
    states[0, 8] = second_theta
    states[0, 12:20] = torch.tensor([0.8, 0.3, 0.0, 0.0, 0.8, 0.3, 0.0, 0.0])
    states[0, 20] = tau_nm
    start = torch.tensor([-half - 0.01, 0.0])
    velocity = SPEED_MPS * torch.tensor([math.cos(pd_rad), math.sin(pd_rad)])
    if is_pull:
        start = torch.tensor([0.0, 0.0])
    inputs = ProcessInput(
        tcp=torch.tensor([*start, 0.0, *velocity, 0.0], dtype=DTYPE),
        pd_rad=torch.tensor(pd_rad, dtype=DTYPE),
        is_pull=torch.tensor(is_pull, dtype=DTYPE),
        link=torch.tensor(0),
        link_size_m=torch.full((2, 2), half, dtype=DTYPE),
        link_offset=torch.tensor([[0.0, 0.0, 0.0], [2 * half, 0.0, second_theta]], dtype=DTYPE),
    )
    return states, inputs


def model(**options: float | str | None) -> AnalyticalProcessModel:
    return TestContext(Path("."), 0).add(AnalyticalProcessModel, **options)


@pytest.mark.parametrize("tau_nm", [0.0, 1.0])
def test_pushing_a_pair_through_its_centre_translates_it(tau_nm: float) -> None:
    """Pushed along the line of both CoMs, welded or free, the pair moves straight at the
    pusher's speed against the friction of both links."""
    states, inputs = chain_scenario(tau_nm)
    prediction = model().predict(states, inputs, DT_S)
    pose = prediction.pose.reshape(2, 6)
    close(pose[:, 3:], torch.tensor([[SPEED_MPS, 0, 0]] * 2, dtype=DTYPE), 1e-8)
    friction_n = 2 * 0.3 * 0.8 * 9.81
    close(prediction.force_n[0] / friction_n, torch.tensor([-1.0, 0.0], dtype=DTYPE), 1e-6)


def test_a_welded_pair_turns_as_one_and_a_free_hinge_folds() -> None:
    """An offset push (the pad 30 mm above link 0's centre, pushing along +x): welded, both
    links turn at one rate about the pair; with a free hinge link 0 turns the other way round
    from link 1, which is dragged by its hinge."""
    welded, inputs = chain_scenario(5.0)
    inputs = dataclasses.replace(inputs, tcp=inputs.tcp + torch.tensor([0, 0.03, 0, 0, 0, 0]))
    rigid = model(pad_half_width_m=0.0).predict(welded, inputs, DT_S).pose.reshape(2, 6)
    assert rigid[0, 5] < 0 and rigid[0, 5] == pytest.approx(float(rigid[1, 5]), rel=1e-3)
    free = welded.clone()
    free[0, 20] = 0.0
    folding = model(pad_half_width_m=0.0).predict(free, inputs, DT_S).pose.reshape(2, 6)
    assert folding[0, 5] < 0 < folding[1, 5]


def test_a_pulled_chain_trails_its_free_link_and_holds_a_stiff_one() -> None:
    """Pulling link 0 along +x by a rigid grasp with link 1 turned by 0.3 rad: a free hinge
    lets link 1 turn back towards the line of pulling; a stiff one holds it."""
    free, inputs = chain_scenario(0.0, is_pull=1.0, second_theta=0.3)
    trailing = model(grasp_friction_nm=None).predict(free, inputs, DT_S).pose.reshape(2, 6)
    torch.testing.assert_close(trailing[0, 3:], torch.tensor([SPEED_MPS, 0, 0], dtype=DTYPE))
    assert trailing[1, 5] < 0
    stiff = free.clone()
    stiff[0, 20] = 1.0
    held = model(grasp_friction_nm=None).predict(stiff, inputs, DT_S).pose.reshape(2, 6)
    close(held[1, 3:], torch.tensor([SPEED_MPS, 0, 0], dtype=DTYPE), 1e-5)


def test_push_normal_against_a_turned_face() -> None:
    """A square turned by 0.7 rad, pushed along +x at the point of its face on the line of its
    centre: with the push direction as normal it moves straight with the pusher; with the box
    side's normal the push lies outside the friction cone (tan 0.7 > mu 0.5), the pad slips
    and its force lies on the cone edge nearer the push, at 0.7 - atan(0.5) rad."""
    turn = 0.7
    states = torch.zeros(1, 10, dtype=DTYPE)
    states[0, 2] = turn
    states[0, 6:8] = torch.tensor([0.8, 0.3])
    face_x = -0.045 / math.cos(turn)
    inputs = ProcessInput(
        tcp=torch.tensor([face_x - 0.01, 0.0, 0.0, SPEED_MPS, 0.0, 0.0], dtype=DTYPE),
        pd_rad=torch.tensor(0.0, dtype=DTYPE),
        is_pull=torch.tensor(0.0, dtype=DTYPE),
        link=torch.tensor(0),
        link_size_m=torch.full((1, 2), 0.045, dtype=DTYPE),
        link_offset=torch.zeros(1, 3, dtype=DTYPE),
    )
    pushed = model().predict(states, inputs, DT_S)
    straight = torch.tensor([SPEED_MPS, 0, 0], dtype=DTYPE)
    torch.testing.assert_close(pushed.pose[0, 3:], straight, rtol=0, atol=1e-9)
    force = -model(contact_normal="box").predict(states, inputs, DT_S).force_n[0]
    angle = math.atan2(float(force[1]), float(force[0]))
    assert angle == pytest.approx(turn - math.atan(0.5), abs=1e-9)


def test_a_weightless_flap_on_a_free_hinge_does_not_fly_off() -> None:
    """A sigma point of a filter run: link 0 nearly weightless (f_max 8e-6 N) on a free hinge,
    pushed obliquely to the box side's normal. Slipping along a cone edge, the contact would
    have had to move 1e11 times faster than the pusher; the contact sticks instead and no
    link moves faster than MAX_SLIP_SPEEDUP times the pusher."""
    twist_map = torch.tensor([[[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]],
                              [[1.0, 0.0, -0.0377, -0.0405], [0.0, 1.0, 0.1355, 0.0161],
                               [0.0, 0.0, 1.0, 1.0]]], dtype=DTYPE)[None]  # fmt: skip
    none = torch.zeros(1, 3, 4, dtype=DTYPE)
    links = chain.ChainProblem(
        twist_map, torch.tensor([[0.0698, 0.0521]], dtype=DTYPE),
        torch.tensor([[7.7772e-06, 2.3516]], dtype=DTYPE), torch.zeros(1, 1, dtype=DTYPE),
        none, none[..., 0], none[..., 0].bool(),
    )  # fmt: skip
    rows = torch.tensor([[[1.0, 0.0, 0.0477, 0.0], [0.0, 1.0, 0.1193, 0.0]]], dtype=DTYPE)
    velocity = torch.tensor([[-2.0110e-02, 6.3739e-05]], dtype=DTYPE)
    normal = torch.tensor([[-0.3449, 0.9386]], dtype=DTYPE)
    motion = chain.push_motion(links, rows, normal, velocity, 0.5)
    speed = chain.link_twists(links, motion.z)[..., :2].norm(dim=-1)
    assert float(speed.max()) <= chain.MAX_SLIP_SPEEDUP * float(velocity.norm())
    close((rows @ motion.z.unsqueeze(-1))[..., 0], velocity, 1e-9)  # it sticks


@pytest.mark.parametrize("n_links", [1, 2])
def test_a_link_turns_in_a_weak_grasp_until_its_friction_holds_it(n_links: int) -> None:
    """Pulling along +x by a grasp 30 mm to the +y side of link 0's CoM: a rigid grasp drags
    the object straight; a grasp holding 0.02 N m lets the link turn clockwise (the CoM swings
    behind the grasp) while the friction's moment about the grasp point equals what the grasp
    holds; one holding 10 N m does not let it turn."""
    states = torch.zeros(1, 11 * n_links - 1, dtype=DTYPE)
    layout = StateLayout(n_links)
    params = layout.parameter_slice.start
    for link in range(n_links):
        states[0, 6 * link] = 0.094 * link
        states[0, params + 4 * link : params + 4 * link + 2] = torch.tensor([0.8, 0.3])
    if n_links > 1:
        states[0, -1] = 5.0  # a stiff hinge
    inputs = ProcessInput(
        tcp=torch.tensor([0.0, 0.03, 0.0, SPEED_MPS, 0.0, 0.0], dtype=DTYPE),
        pd_rad=torch.tensor(0.0, dtype=DTYPE),
        is_pull=torch.tensor(1.0, dtype=DTYPE),
        link=torch.tensor(0),
        link_size_m=torch.full((n_links, 2), 0.045, dtype=DTYPE),
        link_offset=torch.tensor([[0.094 * k, 0.0, 0.0] for k in range(n_links)], dtype=DTYPE),
    )
    rates = {}
    for grasp in (None, 0.02, 10.0):
        pose = model(grasp_friction_nm=grasp).predict(states, inputs, DT_S).pose
        rates[grasp] = float(pose.reshape(n_links, 6)[0, 5])
    assert rates[None] == pytest.approx(0.0, abs=1e-12)
    assert rates[0.02] < -0.01 and abs(rates[10.0]) < 1e-4
    # Statics: about the grasp point the links' friction needs the grasp's full torque, 0.02
    # N m counter-clockwise, against the link's clockwise turn.
    links, com = chain.chain_links(states[None], inputs)
    held_map = links.twist_map[:, :, 0]
    grasp_rows = chain.point_velocity_rows(held_map, com[:, :, 0], inputs.tcp[:2].expand(1, 1, 2))
    motion = chain.pull_motion(links, held_map, grasp_rows, inputs.tcp[3:].expand(1, 1, 3), 0.02)
    arm = com - inputs.tcp[:2]
    moment = (_cross(arm, motion.wrench[..., :2]) + motion.wrench[..., 2]).sum(-1)
    close(moment, 0.02, 1e-4)
