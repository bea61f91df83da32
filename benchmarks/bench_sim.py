"""Simulation speed: a 5 s push at 15 Hz with the filter's observations, and one depth view.

Targets (issue: framework core): the push runs >= 20x faster than real time with a 64x64
depth image and the tactile forces at every step; a 320x240 view takes < 10 ms. Peers in the
same run: bare MuJoCo stepping of the same model (no observations), and a raw mj_multiRay
call over the same 320x240 rays (no noise, no back-projection).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import mujoco
import numpy as np
from common import Row, median_time_s
from vistac.testing import build_components
from vistac.types import Push

ROOT = Path(__file__).resolve().parents[1]
PUSH_S = 5.0
RATE_HZ = 15.0


def _components(width: int, height: int) -> dict[str, dict[str, object]]:
    return {
        "world": {
            "plugin": "sim.mujoco",
            "with": {"object": str(ROOT / "skills/objects/rect2.yaml")},
        },
        "arm": {"plugin": "sim.arm"},
        "gripper": {"plugin": "sim.gripper"},
        "camera": {"plugin": "sim.depth_camera", "with": {"width": width, "height": height}},
        "tactile": {"plugin": "sim.tactile"},
        "executor": {"plugin": "actions.cartesian"},
    }


def _push_periods(ctx: object) -> tuple[object, object]:
    """Run the executor up to the start of the push; returns (executor, context)."""
    executor = ctx.component("executor")  # type: ignore[attr-defined]
    executor.start(Push(np.array([0.0, 0.39]), np.pi / 2, 0.02, duration_s=PUSH_S))
    while not executor.step(1 / RATE_HZ)[1]:
        ctx.clock.advance(1 / RATE_HZ)  # type: ignore[attr-defined]
    return executor, ctx


def time_push_s(repeats: int) -> float:
    """Median wall time of the 75 observed periods of a 5 s push."""
    samples = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats + 1):
            ctx = build_components(_components(64, 64), Path(tmp))
            executor, _ = _push_periods(ctx)
            camera, tactile, arm = (ctx.component(r) for r in ("camera", "tactile", "arm"))
            world = ctx.world_if_built()

            def push(executor=executor, ctx=ctx, tactile=tactile, arm=arm,
                     camera=camera, world=world) -> None:
                for _ in range(round(PUSH_S * RATE_HZ)):
                    executor.step(1 / RATE_HZ)
                    ctx.clock.advance(1 / RATE_HZ)
                    tactile.read(), arm.state(), camera.capture(64, 64), world.ground_truth_poses()

            samples.append(median_time_s(push, 1, warmup=0))
    return float(np.median(samples[1:]))


def time_bare_steps_s(repeats: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        world = build_components(_components(64, 64), Path(tmp)).world_if_built()
        steps = round(PUSH_S / world.model.opt.timestep)
        return median_time_s(lambda: mujoco.mj_step(world.model, world.data, nstep=steps), repeats)


def time_views_s(repeats: int) -> tuple[float, float]:
    """(vistac capture, raw mj_multiRay) median seconds for a 320x240 view."""
    with tempfile.TemporaryDirectory() as tmp:
        ctx = build_components(_components(320, 240), Path(tmp))
        camera, world = ctx.component("camera"), ctx.world_if_built()
        capture_s = median_time_s(camera.capture, repeats)
        rays = camera.intrinsics.pixel_rays().reshape(-1, 3) @ camera.world_from_camera[:3, :3].T
        rays = np.ascontiguousarray(rays)
        count = len(rays)
        geom_id, dist = np.empty(count, dtype=np.int32), np.empty(count)
        origin = np.ascontiguousarray(camera.world_from_camera[:3, 3])

        def raw() -> None:
            mujoco.mj_multiRay(
                world.model,
                world.data,
                origin,
                rays.ravel(),
                None,
                1,
                -1,
                geom_id,
                dist,
                None,
                count,
                10.0,
            )

        return capture_s, median_time_s(raw, repeats)


def run(repeats: int) -> list[Row]:
    push_s = time_push_s(repeats)
    bare_s = time_bare_steps_s(repeats)
    capture_s, raw_s = time_views_s(repeats * 3)
    return [
        Row(
            "5 s push @15 Hz (tactile + 64x64 depth + poses per step), speed-up over real time",
            PUSH_S / push_s,
            "x",
            ">= 20x",
            PUSH_S / push_s >= 20,
            "bare mj_step, no observations",
            PUSH_S / bare_s,
            f"{push_s * 1e3:.0f} ms wall for 5 s simulated",
        ),
        Row(
            "one 320x240 depth view (sim.depth_camera.capture)",
            capture_s * 1e3,
            "ms",
            "< 10 ms",
            capture_s < 0.010,
            "raw mj_multiRay, same rays",
            raw_s * 1e3,
            "includes noise, dropouts, range limits",
        ),
    ]
