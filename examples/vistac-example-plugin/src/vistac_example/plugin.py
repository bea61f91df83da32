"""Entry-point module: registers the component and implements the observer hooks."""

from __future__ import annotations

import csv
from typing import IO, Any

from vistac import hookimpl

_files: dict[str, tuple[IO[str], Any]] = {}


@hookimpl
def vistac_register(registry: Any) -> None:
    # Imported only when a skill uses it.
    registry.add("camera", "example.noisy_camera", "vistac_example.noisy_camera:NoisyCamera")
    registry.add("process_model", "example.rigid_push", "vistac_example.rigid_push:RigidPush")


@hookimpl
def vistac_skill_start(run: Any) -> None:
    handle = open(run.out_dir / "tactile.csv", "w", newline="")  # noqa: SIM115 - closed at skill end
    writer = csv.writer(handle)
    writer.writerow(["episode", "step", "time_s", "pad", "fx_n", "fy_n"])
    _files[str(run.out_dir)] = (handle, writer)


@hookimpl
def vistac_observation(run: Any, episode: int, step: int, observation: Any) -> None:
    _, writer = _files[str(run.out_dir)]
    for pad, (fx, fy) in enumerate(observation.tactile.force_n):
        writer.writerow([episode, step, f"{observation.time_s:.4f}", pad, f"{fx:.5f}", f"{fy:.5f}"])


@hookimpl
def vistac_skill_end(run: Any, status: str, summary: dict[str, Any]) -> None:
    handle, _ = _files.pop(str(run.out_dir), (None, None))
    if handle is not None:
        handle.close()
