"""Simulation speed: a 5 s push at 15 Hz with the filter's observations, and one depth view.

Targets (issue: framework core): the push runs >= 20x faster than real time with a 64x64
depth image and the tactile forces at every step; a 320x240 view takes < 10 ms. Peers in the
same run: the same push without observations (the executor and the physics only), and a raw
mj_multiRay call over the same 320x240 rays in the camera's two threads (no noise, no
back-projection).
"""

from __future__ import annotations

import itertools
import tempfile
from concurrent.futures import ThreadPoolExecutor
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
    camera = {"width": width, "height": height, "ray_threads": RAY_THREADS}
    return {
        "world": {
            "plugin": "sim.mujoco",
            "with": {"object": str(ROOT / "skills/objects/rect2.yaml")},
        },
        "arm": {"plugin": "sim.arm"},
        "gripper": {"plugin": "sim.gripper"},
        "camera": {"plugin": "sim.depth_camera", "with": camera},
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


def time_push_s(repeats: int, observe: bool = True) -> float:
    """Median wall time of the 75 periods of a 5 s push, each observed (tactile, arm state,
    64x64 depth, poses) unless not ``observe``."""
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
                    if observe:
                        tactile.read(), arm.state(), camera.capture(64, 64)
                        world.ground_truth_poses()

            samples.append(median_time_s(push, 1, warmup=0))
    return float(np.median(samples[1:]))


RAY_THREADS = 2
"""The camera's default; the raw peer casts the same rays in as many threads."""


def time_views_s(repeats: int) -> tuple[float, float]:
    """(vistac capture, raw mj_multiRay) median seconds for a 320x240 view, both cast in
    ``RAY_THREADS`` threads over the same halves of the rays."""
    with tempfile.TemporaryDirectory() as tmp:
        ctx = build_components(_components(320, 240), Path(tmp))
        camera, world = ctx.component("camera"), ctx.world_if_built()
        capture_s = median_time_s(camera.capture, repeats)
        rays = camera.intrinsics.pixel_rays().reshape(-1, 3) @ camera.world_from_camera[:3, :3].T
        rays = np.ascontiguousarray(rays)
        count = len(rays)
        geom_id, dist = np.empty(count, dtype=np.int32), np.empty(count)
        origin = np.ascontiguousarray(camera.world_from_camera[:3, 3])
        bounds = np.linspace(0, count, RAY_THREADS + 1).astype(int)

        def cast(chunk: slice) -> None:
            mujoco.mj_multiRay(world.model, world.data, origin, rays[chunk].ravel(), None, 1,
                               -1, geom_id[chunk], dist[chunk], None, chunk.stop - chunk.start,
                               10.0)  # fmt: skip

        chunks = [slice(int(a), int(b)) for a, b in itertools.pairwise(bounds)]
        with ThreadPoolExecutor(RAY_THREADS) as pool:  # mj_multiRay releases the GIL
            raw_s = median_time_s(lambda: list(pool.map(cast, chunks)), repeats)
        return capture_s, raw_s


def run(repeats: int) -> list[Row]:
    push_s = time_push_s(repeats)
    bare_s = time_push_s(repeats, observe=False)
    capture_s, raw_s = time_views_s(repeats * 3)
    return [
        Row(
            "5 s push @15 Hz (tactile + 64x64 depth + poses per step), speed-up over real time",
            PUSH_S / push_s,
            "x",
            ">= 20x",
            PUSH_S / push_s >= 20,
            "the same push without observations",
            PUSH_S / bare_s,
            f"{push_s * 1e3:.0f} ms wall for 5 s simulated",
        ),
        Row(
            "one 320x240 depth view (sim.depth_camera.capture)",
            capture_s * 1e3,
            "ms",
            "< 10 ms",
            capture_s < 0.010,
            f"raw mj_multiRay, same rays, same {RAY_THREADS} threads",
            raw_s * 1e3,
            "includes noise, dropouts, range limits",
        ),
    ]
