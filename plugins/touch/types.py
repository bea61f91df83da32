"""Types shared by the touch components: the particle filter publishes its most likely
shape through ``MlePrior`` so that the surface reconstruction can use it as prior mean."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from vistac.types import FloatArray

SignedDistance = Callable[[FloatArray], tuple[FloatArray, FloatArray]]
"""points [N, 3] (world, m) -> (signed distance [N] in m, positive outside; unit outward
normal of the nearest surface point [N, 3])."""


@dataclass(frozen=True)
class MlePrior:
    """The maximum-likelihood (class, pose) of a recogniser.

    world_from_object: [4, 4] homogeneous pose; vertices_m: [V, 3] and triangles: [T, 3] the
    class mesh in the world frame at that pose; sdf: its signed distance in the world frame.
    """

    class_name: str
    probability: float
    world_from_object: FloatArray
    vertices_m: FloatArray
    triangles: FloatArray
    sdf: SignedDistance
