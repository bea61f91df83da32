"""What quasi-static pushes show of a welded pair, and the best estimate from that alone.

The force of a slow push balances the table's friction, so it shows a rigid body's total
friction load ``sum(m_i f_i)`` (times g); the motion it causes shows where that load is
centred, ``p = sum(m_i f_i c_i) / sum(m_i f_i)``. Of a single link that is ``m f`` and its
CoM. Of a welded pair (a heterogeneous object) it is three numbers for eight parameters: how
the load splits between the links, each link's m against its f, and each CoM along the line
through ``p`` stay open.

:func:`welded_pair_posterior` is the Bayes estimate of every link's m, f and CoM from the
pair's load and load centre known exactly, under the object set's sampling distributions
(:mod:`vistac.objects`: m and f uniform over their ranges, each CoM uniform inside its
footprint shrunk by :data:`vistac.objects.COM_SHRINK`). It conditions exactly by importance
sampling: m_0, f_0, m_1 and c_0 are drawn from the prior, f_1 and c_1 solved from the load
and its centre, and each draw weighted by the inverse Jacobian of that solution,
``(1 / m_1) (L / l_1)^2`` with ``l_1 = m_1 f_1`` and ``L`` the total load (zero where f_1 or
c_1 falls outside its range). On average over the object set, no estimator that uses only the
load and its centre errs less: the ``load known`` reference of ``vistac eval``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from vistac.objects import (
    COM_SHRINK,
    FRICTION_RANGE,
    MASS_RANGE_KG,
    ObjectSpec,
    attachment,
    points_inside,
    uniform_inside,
)

FloatArray = NDArray[np.float64]

POSTERIOR_SAMPLES = 200_000
"""Importance samples per object: the posterior means move by 0.006 of the parameter ranges
or less between sampling seeds."""


@dataclass(frozen=True)
class WeldedSamples:
    """Draws of a welded pair's parameters that all have the given load and load centre.

    mass_kg, friction: [N, 2] per draw and link; com_m: [N, 2, 2] each link's CoM in its own
    frame; weight: [N] normalised importance weights (zero for draws outside the ranges).
    """

    mass_kg: FloatArray
    friction: FloatArray
    com_m: FloatArray
    weight: FloatArray


def pair_load(spec: ObjectSpec) -> tuple[float, FloatArray]:
    """A two-link object's total friction load sum(m f) (kg; times g it is the force) and its
    centre [2] (m, in link 0's frame)."""
    offset, _ = attachment(spec)
    loads = np.array([link.mass_kg * link.friction for link in spec.links])
    centres = np.array([spec.links[0].com_m, offset + np.asarray(spec.links[1].com_m)])
    return float(loads.sum()), loads @ centres / loads.sum()


def welded_pair_samples(spec: ObjectSpec, count: int, rng: np.random.Generator) -> WeldedSamples:
    """Posterior draws of a two-link object's parameters given its :func:`pair_load`."""
    if len(spec.links) != 2:
        raise ValueError(f"{spec.name}: a welded pair has 2 links, not {len(spec.links)}")
    load, centre = pair_load(spec)
    offset, _ = attachment(spec)
    mass = rng.uniform(MASS_RANGE_KG[0], MASS_RANGE_KG[1], (count, 2))
    friction_0 = rng.uniform(FRICTION_RANGE[0], FRICTION_RANGE[1], count)
    com_0 = uniform_inside(COM_SHRINK * spec.links[0].polygon(), count, rng)
    load_0 = mass[:, 0] * friction_0
    load_1 = load - load_0
    positive = load_1 > 0
    safe_load_1 = np.where(positive, load_1, 1.0)
    friction_1 = load_1 / mass[:, 1]
    com_1 = (load * centre - load_0[:, None] * com_0) / safe_load_1[:, None] - offset
    feasible = (
        positive
        & (friction_1 >= FRICTION_RANGE[0])
        & (friction_1 <= FRICTION_RANGE[1])
        & points_inside(COM_SHRINK * spec.links[1].polygon(), com_1)
    )
    weight = np.where(feasible, (load / safe_load_1) ** 2 / mass[:, 1], 0.0)
    if weight.sum() <= 0:
        raise ValueError(f"{spec.name}: no feasible draw in {count} samples")
    return WeldedSamples(
        mass_kg=mass,
        friction=np.stack([friction_0, friction_1], axis=1),
        com_m=np.stack([com_0, com_1], axis=1),
        weight=weight / weight.sum(),
    )


def welded_pair_posterior(
    spec: ObjectSpec, count: int = POSTERIOR_SAMPLES, seed: int = 0
) -> list[tuple[float, float, FloatArray]]:
    """Posterior means (mass kg, friction, CoM [2] m in the link's frame) of each link of a
    two-link object, given its total friction load and load centre exactly."""
    samples = welded_pair_samples(spec, count, np.random.default_rng(seed))
    mass = samples.weight @ samples.mass_kg
    friction = samples.weight @ samples.friction
    com = np.einsum("n,nlc->lc", samples.weight, samples.com_m)
    return [(float(mass[i]), float(friction[i]), com[i]) for i in range(2)]
