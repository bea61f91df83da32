"""``vistac replay``: a recorded run's belief updates, again, offline.

A run whose tree has ``update_belief`` keeps what its filter saw: the shape and object cloud
the filter started from (``filter_start`` in summary.json, ``views/object_cloud.npz``) and
each interaction's stream (``episodes/NNNN/``). Replay feeds them through the filter of the
run's own skill, changed by ``--set`` (another process model, checkpoint, prior, number of
sigma points), with no world, arm or camera built: what another filter or model makes of
the same recorded interactions, real-robot runs included. Only the updates are replayed: a
tree that also corrects the belief from later looks (``plan_push``'s ``look_std_m``) did more.

The output folder gets ``run.json`` (the source run, the overrides, versions) and
``summary.json`` (prior, belief, belief_history, filter_steps, and where the source run knew
the truth, belief_truth and errors).
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
from vistac.behaviours.belief import record_belief
from vistac.behaviours.look import shape_from_links
from vistac.errors import ConfigError, ConfigIssue
from vistac.pluginmanager import Plugins
from vistac.protocols import Episode, Scene, StepObservation
from vistac.recording import RunRecorder, check_out_dir, prepare_out_dir
from vistac.run import RunContext
from vistac.scheduler import add_belief_errors, run_info
from vistac.skill import apply_overrides, validate_skill
from vistac.types import (
    RGBD,
    ArmState,
    CameraIntrinsics,
    PointCloud,
    ShapeEstimate,
    TactileReading,
    action_from_dict,
)

log = logging.getLogger(__name__)


def replay(
    run_dir: Path,
    out_dir: Path,
    plugins: Plugins,
    overrides: list[str] | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """Replay ``run_dir``'s belief updates into ``out_dir``; returns the new summary."""
    _refuse_overlap(run_dir, out_dir)
    source, summary = _read_json(run_dir, "run.json"), _read_json(run_dir, "summary.json")
    if not isinstance(source.get("config"), dict) or "skill_path" not in source:
        raise _bad_run(f"{run_dir / 'run.json'}: no skill config or skill_path in it")
    data = apply_overrides(source["config"], list(overrides or []))
    skill = validate_skill(data, Path(source["skill_path"]), plugins.registry)
    roles = [role for role, c in skill.components.items() if c.kind == "filter"]
    if not roles:
        raise ConfigError([ConfigIssue("components", "the run's skill has no filter to replay")])
    shape = _filter_start(run_dir, summary)
    episodes = sorted(p for p in (run_dir / "episodes").glob("[0-9]*") if p.is_dir())
    check_out_dir(out_dir, overwrite)
    seed = int(source.get("seed", skill.seed))
    ctx = RunContext(skill, plugins, RunRecorder(out_dir), seed)
    try:  # bad input (a checkpoint that is not there) stops here, before the folder is made
        belief_filter = ctx.component(roles[0])
    except BaseException:
        ctx.close_all()
        raise
    prepare_out_dir(out_dir, overwrite)
    info = {**run_info(skill, plugins, seed), "replay_of": str(run_dir),
            "overrides": list(overrides or [])}  # fmt: skip
    start_s = time.perf_counter()
    try:
        results = _updates(belief_filter, shape, episodes)
    except Exception as error:  # the folder says why it holds no summary
        info.update(status="error", error=f"{type(error).__name__}: {error}")
        ctx.recorder.write_run(info)
        raise
    finally:
        ctx.close_all()
    new = _summary(summary, results, time.perf_counter() - start_s)
    info.update(status="success", error=None, wall_time_s=new["wall_time_s"])
    ctx.recorder.write_summary(new)
    ctx.recorder.write_run(info)
    return new


def _updates(filter_: Any, shape: ShapeEstimate, episodes: list[Path]) -> dict[str, Any]:
    """Initialise ``filter_`` on ``shape`` and update it with each episode folder in turn:
    the summary entries ``update_belief`` writes, and ``prior``."""
    results: dict[str, Any] = {"prior": filter_.initialise(Scene(shape.cloud, shape)).as_dict()}
    for folder in episodes:
        belief = filter_.update(load_episode(folder))
        record_belief(results, belief)
        results.setdefault("belief_history", []).append(belief.as_dict())
        log.info("replayed %s", folder.name)
    steps = getattr(filter_, "step_history", None)
    if callable(steps):
        results["filter_steps"] = steps()
    return results


def _summary(source: dict[str, Any], results: dict[str, Any], wall_s: float) -> dict[str, Any]:
    """The replay's summary: the source's skill, seed, episodes and truth, the new belief."""
    summary: dict[str, Any] = {
        "skill": source.get("skill"),
        "status": "success",
        "error": None,
        "seed": source.get("seed"),
        "wall_time_s": wall_s,
        "episodes": source.get("episodes", []),
        "shape": source.get("shape"),
        **results,
        "ground_truth": source.get("ground_truth"),
    }
    add_belief_errors(summary)
    return summary


def _refuse_overlap(run_dir: Path, out_dir: Path) -> None:
    """A ConfigError (exit 2) when ``out_dir`` is ``run_dir`` or one holds the other: writing
    the replay there would delete or mix with the recording it replays."""
    run, out = run_dir.resolve(), out_dir.resolve()
    if out.is_relative_to(run) or run.is_relative_to(out):
        raise ConfigError([ConfigIssue("--out", f"{out_dir} overlaps the replayed run {run_dir} "
                                       "(the same folder or one inside the other); choose a "
                                       "folder outside it")])  # fmt: skip


def _bad_run(message: str) -> ConfigError:
    """Invalid input (exit 2): the folder is no run replay can use."""
    return ConfigError([ConfigIssue("RUN", message)])


def _read_json(run_dir: Path, name: str) -> dict[str, Any]:
    path = run_dir / name
    try:
        data: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise _bad_run(f"{path}: not found; give the folder of a `vistac run`") from None
    except json.JSONDecodeError as error:
        raise _bad_run(f"{path}: not JSON ({error})") from None
    return data


def _filter_start(run_dir: Path, summary: dict[str, Any]) -> ShapeEstimate:
    """The shape the run's filter started from, with its object cloud."""
    cloud_path = run_dir / "views" / "object_cloud.npz"
    start = summary.get("filter_start")
    if start is None or not cloud_path.exists():
        raise _bad_run(
            f"{run_dir}: no filter_start in summary.json or no views/object_cloud.npz: the run "
            "never initialised a filter, or was recorded by a vistac older than `replay`; "
            "record it again"
        )
    with np.load(cloud_path, allow_pickle=False) as arrays:
        cloud = PointCloud(arrays["points_m"].astype(np.float64))
    return shape_from_links(start["links"], cloud)


def load_episode(folder: Path) -> Episode:
    """The Episode ``RunRecorder.save_episode`` wrote to ``folder``."""
    meta = _read_json(folder, "meta.json")
    with np.load(folder / "data.npz", allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    steps = [_step(arrays, t) for t in range(len(arrays["time_s"]))]
    return Episode(int(meta["index"]), action_from_dict(meta["action"]), steps,
                   str(meta.get("outcome", "ok")))  # fmt: skip


def _step(arrays: dict[str, np.ndarray], t: int) -> StepObservation:
    """Step t of an episode's arrays (``vistac.recording.episode_arrays``)."""
    time_s = float(arrays["time_s"][t])
    tactile_s = float(arrays["tactile_time_s"][t]) if "tactile_time_s" in arrays else time_s
    depth = None
    if "depth_m" in arrays:
        image = arrays["depth_m"][t].astype(np.float64)
        fx, fy, cx, cy = (float(v) for v in arrays["depth_intrinsics"][t])
        intrinsics = CameraIntrinsics(image.shape[1], image.shape[0], fx, fy, cx, cy)
        depth = RGBD(image, intrinsics, arrays["camera_pose"][t], time_s)
    truth = arrays["object_pose"][t] if "object_pose" in arrays else None
    return StepObservation(
        time_s,
        TactileReading(arrays["tactile_force_n"][t], tactile_s),
        ArmState(arrays["arm_pose"][t], arrays["arm_twist"][t], time_s),
        depth,
        truth,
    )
