"""Simulated tactile pads: the 2D contact force on each finger pad from ``mj_contactForce``."""

from __future__ import annotations

import mujoco
import numpy as np
from pydantic import Field
from vistac.component import Component, ComponentConfig, ComponentContext
from vistac.plugins.hardware.sim.arm import find_world
from vistac.types import FloatArray, TactileReading


def pad_forces(model: mujoco.MjModel, data: mujoco.MjData, pads: np.ndarray) -> FloatArray:
    """The force the other geoms of their contacts exert on each pad geom in ``pads`` [P]:
    [P, 3] (world frame, N)."""
    forces = np.zeros((len(pads), 3))
    wrench = np.zeros(6)
    pad_index = {geom: k for k, geom in enumerate(pads.tolist())}
    frames = data.contact.frame
    for i, (geom1, geom2) in enumerate(data.contact.geom[: data.ncon].tolist()):
        if geom1 not in pad_index and geom2 not in pad_index:
            continue
        mujoco.mj_contactForce(model, data, i, wrench)
        # The contact force acts on geom2 along the frame (normal from geom1 to geom2).
        on_geom2 = frames[i].reshape(3, 3).T @ wrench[:3]
        if geom2 in pad_index:
            forces[pad_index[geom2]] += on_geom2
        if geom1 in pad_index:
            forces[pad_index[geom1]] -= on_geom2
    return forces


class SimTactile(Component):
    """Implements the ``Tactile`` protocol.

    Per pad: the sum over the pad geom's contacts of the force the other geom (the object)
    exerts on the pad, in the world frame, x and y components, plus Gaussian noise of
    ``noise_n`` (stream ``"tactile"``). ``bias`` subtracts the current noise-free reading.
    """

    kind = "tactile"

    class Config(ComponentConfig):
        noise_n: float = Field(default=0.02, ge=0.0)

    def __init__(self, config: Config, ctx: ComponentContext) -> None:
        super().__init__(config, ctx)
        self.world = find_world(ctx, "sim.tactile")
        self._rng = ctx.rng("tactile")
        self._bias_n = np.zeros((2, 2))

    def pad_forces(self) -> FloatArray:
        """Noise-free, unbiased force on each pad: [2, 3] (world frame, N)."""
        return pad_forces(self.world.model, self.world.data, self.world.index.pad_geoms)

    def read(self) -> TactileReading:
        force_n = self.pad_forces()[:, :2] - self._bias_n
        force_n += self._rng.normal(0.0, self.config.noise_n, size=force_n.shape)
        return TactileReading(force_n=force_n, timestamp_s=self.world.time_s)

    def bias(self) -> None:
        self._bias_n = self.pad_forces()[:, :2]
