"""Writes a run's output folder.

::

    OUT/run.json               config, versions, seed, timings, status
    OUT/views/NNNN.npz         each depth view taken by ``look`` (+ cloud.npz, the merged cloud,
                               and object_cloud.npz, the object cloud a filter started from)
    OUT/episodes/NNNN/data.npz the observation stream of one interaction (arrays)
    OUT/episodes/NNNN/meta.json the action, outcome, units and ground truth when known
    OUT/summary.json           estimates, variances, ground truth and metrics

Arrays are saved with ``np.savez`` and must be read with ``allow_pickle=False``. An episode
folder appears only once complete (written to a temporary name, then renamed).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
from vistac.errors import ConfigError, ConfigIssue
from vistac.protocols import Episode
from vistac.types import RGBD, PointCloud, action_to_dict

RUN_FILES = ("run.json", "summary.json")
RUN_DIRS = ("episodes", "views")


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (temporary file, then rename)."""
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, default=_json_default) + "\n")
    tmp.replace(path)


def refuse_file_as_folder(out_dir: Path) -> None:
    """A ConfigError (exit 2) naming ``--out`` when ``out_dir``, or the nearest existing
    folder above it, is a file: no output folder can be made there."""
    for path in (out_dir, *out_dir.parents):
        if path.exists():
            if not path.is_dir():
                raise ConfigError([ConfigIssue("--out", f"{path} is a file; give a folder")])
            return


def check_out_dir(out_dir: Path, overwrite: bool) -> None:
    """A ConfigError (exit 2) when ``out_dir`` cannot take a run: it or a folder above it is
    a file, or it holds an earlier run and ``overwrite`` is not given. Changes nothing."""
    refuse_file_as_folder(out_dir)
    if (out_dir / "run.json").exists() and not overwrite:
        message = f"{out_dir} already holds a run; choose another folder or pass --overwrite"
        raise ConfigError([ConfigIssue("--out", message)])


def prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir``; refuse to mix with an earlier run unless ``overwrite``, which
    removes the earlier run's files."""
    check_out_dir(out_dir, overwrite)
    if (out_dir / "run.json").exists():
        for name in RUN_FILES:
            (out_dir / name).unlink(missing_ok=True)
        for name in RUN_DIRS:
            shutil.rmtree(out_dir / name, ignore_errors=True)
    out_dir.mkdir(parents=True, exist_ok=True)


def episode_arrays(episode: Episode) -> dict[str, np.ndarray]:
    """Stack an episode's steps into arrays: time_s [T], tactile_force_n [T, P, 2],
    arm_pose [T, 4], arm_twist [T, 4], and when present depth_m [T, h, w] with camera_pose
    [T, 4, 4] (world from optical frame) and depth_intrinsics [T, 4] = (fx, fy, cx, cy) px,
    and object_pose [T, L, 3]."""
    steps = episode.steps
    arrays: dict[str, np.ndarray] = {
        "time_s": np.array([s.time_s for s in steps]),
        "tactile_force_n": np.array([s.tactile.force_n for s in steps]).reshape(len(steps), -1, 2),
        "tactile_time_s": np.array([s.tactile.timestamp_s for s in steps]),
        "arm_pose": np.array([s.arm.pose for s in steps]).reshape(len(steps), 4),
        "arm_twist": np.array([s.arm.twist for s in steps]).reshape(len(steps), 4),
    }
    frames = [s.depth for s in steps]
    if steps and all(frame is not None for frame in frames):
        arrays["depth_m"] = np.stack([f.depth_m for f in frames if f]).astype(np.float32)
        arrays["camera_pose"] = np.stack([f.world_from_camera for f in frames if f])
        arrays["depth_intrinsics"] = np.array(
            [
                [f.intrinsics.fx, f.intrinsics.fy, f.intrinsics.cx, f.intrinsics.cy]
                for f in frames
                if f
            ]
        )
    if steps and all(s.ground_truth_poses is not None for s in steps):
        arrays["object_pose"] = np.stack([s.ground_truth_poses for s in steps])
    return arrays


class RunRecorder:
    """Owns the output folder of one run."""

    def __init__(self, out_dir: Path) -> None:
        self.out_dir = out_dir
        self.episodes: list[dict[str, Any]] = []
        self.views = 0

    def write_run(self, info: dict[str, Any]) -> None:
        write_json(self.out_dir / "run.json", info)

    def write_summary(self, summary: dict[str, Any]) -> None:
        write_json(self.out_dir / "summary.json", summary)

    def save_view(self, rgbd: RGBD) -> Path:
        """Save one depth view: depth_m [H, W], world_from_camera [4, 4], intrinsics [4]."""
        folder = self.out_dir / "views"
        folder.mkdir(exist_ok=True)
        path = folder / f"{self.views:04d}.npz"
        k = rgbd.intrinsics
        np.savez_compressed(
            path,
            depth_m=rgbd.depth_m.astype(np.float32),
            world_from_camera=rgbd.world_from_camera,
            intrinsics_fx_fy_cx_cy=np.array([k.fx, k.fy, k.cx, k.cy]),
            timestamp_s=np.array(rgbd.timestamp_s),
        )
        self.views += 1
        return path

    def save_cloud(self, cloud: PointCloud) -> None:
        folder = self.out_dir / "views"
        folder.mkdir(exist_ok=True)
        np.savez_compressed(folder / "cloud.npz", points_m=cloud.points_m.astype(np.float32))

    def save_object_cloud(self, cloud: PointCloud) -> None:
        """The segmented object cloud a filter started from: views/object_cloud.npz."""
        folder = self.out_dir / "views"
        folder.mkdir(exist_ok=True)
        np.savez_compressed(folder / "object_cloud.npz", points_m=cloud.points_m)

    def save_episode(self, episode: Episode, ground_truth: dict[str, Any] | None) -> Path:
        """Write ``episodes/NNNN/`` atomically and remember its summary line."""
        root = self.out_dir / "episodes"
        root.mkdir(exist_ok=True)
        final = root / f"{episode.index:04d}"
        tmp = root / f".{episode.index:04d}.tmp"
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir()
        arrays = episode_arrays(episode)
        np.savez_compressed(tmp / "data.npz", **arrays)  # type: ignore[arg-type]
        meta = {
            "index": episode.index,
            "action": action_to_dict(episode.action),
            "outcome": episode.outcome,
            "steps": len(episode.steps),
            "arrays": {name: list(a.shape) for name, a in arrays.items()},
            "units": {
                "time_s": "s",
                "tactile_force_n": "N (world x, y per pad)",
                "arm_pose": "x, y, z m, yaw rad",
                "depth_m": "m (NaN: no return)",
                "camera_pose": "world from camera optical frame (x right, y down, z forward)",
                "depth_intrinsics": "fx, fy, cx, cy in pixels of depth_m",
                "object_pose": "x, y m, theta rad per link (ground truth)",
            },
            "ground_truth": ground_truth,
        }
        write_json(tmp / "meta.json", meta)
        shutil.rmtree(final, ignore_errors=True)
        tmp.rename(final)
        self.episodes.append(self._episode_line(episode, arrays))
        return final

    @staticmethod
    def _episode_line(episode: Episode, arrays: dict[str, np.ndarray]) -> dict[str, Any]:
        line: dict[str, Any] = {
            "index": episode.index,
            "action": action_to_dict(episode.action),
            "outcome": episode.outcome,
            "steps": len(episode.steps),
        }
        if "tactile_force_n" in arrays and len(arrays["tactile_force_n"]):
            forces = np.linalg.norm(arrays["tactile_force_n"], axis=-1).sum(axis=-1)
            line["peak_tactile_force_n"] = float(forces.max())
        if "object_pose" in arrays and len(arrays["object_pose"]) > 1:
            poses = arrays["object_pose"]
            line["object_displacement_m"] = np.linalg.norm(
                poses[-1, :, :2] - poses[0, :, :2], axis=-1
            ).tolist()
            line["object_rotation_rad"] = (poses[-1, :, 2] - poses[0, :, 2]).tolist()
        return line
