"""Point-pair features (Drost et al., CVPR 2010) for touch: the feature of two oriented
points, a hash table over a model's surface samples, and the rigid pose aligning a model pair
to an observed pair.

F(m1, m2) = (|d|, angle(n1, d), angle(n2, d), angle(n1, n2)) with d = m2 - m1.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from vistac.types import FloatArray

log = logging.getLogger(__name__)

IntArray = NDArray[np.int64]


def _angle(a: FloatArray, b: FloatArray) -> FloatArray:
    """Angle in [0, pi] between vectors a [N, 3] and b [N, 3] (robust at 0 and pi)."""
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    return np.arctan2(cross, np.sum(a * b, axis=-1))


def point_pair_features(
    p1: FloatArray, n1: FloatArray, p2: FloatArray, n2: FloatArray
) -> FloatArray:
    """Features [N, 4] (distance m, three angles rad) of pairs (p1, n1) -> (p2, n2), each [N, 3]."""
    d = p2 - p1
    return np.stack([np.linalg.norm(d, axis=-1), _angle(n1, d), _angle(n2, d), _angle(n1, n2)], -1)


@dataclass(frozen=True)
class Quantisation:
    """Bin sizes: distance in m, angles in rad."""

    distance_m: float
    angle_rad: float

    def keys(self, features: FloatArray) -> IntArray:
        """One int64 key per feature row [N, 4]."""
        bins = np.rint(features / [self.distance_m, *[self.angle_rad] * 3]).astype(np.int64)
        angle_bins = int(np.ceil(np.pi / self.angle_rad)) + 1
        key = bins[:, 0]
        for column in range(1, 4):
            key = key * angle_bins + bins[:, column]
        return np.asarray(key, dtype=np.int64)


class PpfTable:
    """All ordered pairs of one model's samples, sorted by quantised feature.

    points [M, 3], normals [M, 3] in the object frame; ``lookup(keys)`` returns the pairs
    (first index [K], second index [K], which query [K]) whose key equals a query key."""

    def __init__(self, points: FloatArray, normals: FloatArray, quantisation: Quantisation) -> None:
        start_s = time.perf_counter()
        self.points, self.normals, self.quantisation = points, normals, quantisation
        count = len(points)
        first, second = np.nonzero(~np.eye(count, dtype=bool))
        keys = quantisation.keys(
            point_pair_features(points[first], normals[first], points[second], normals[second])
        )
        order = np.argsort(keys, kind="stable")
        self.keys, self.first, self.second = keys[order], first[order], second[order]
        self.build_s = time.perf_counter() - start_s

    def lookup(self, keys: IntArray) -> tuple[IntArray, IntArray, IntArray]:
        """Model pairs matching each query key: (first [K], second [K], query index [K])."""
        low = np.searchsorted(self.keys, keys, side="left")
        high = np.searchsorted(self.keys, keys, side="right")
        counts = high - low
        query = np.repeat(np.arange(len(keys)), counts)
        offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        rows = np.repeat(low, counts) + offsets
        return self.first[rows], self.second[rows], query


def frame_to_x(points: FloatArray, normals: FloatArray) -> FloatArray:
    """Rigid transforms [N, 4, 4] moving each point to the origin and its normal onto +x."""
    x = np.array([1.0, 0.0, 0.0])
    axis = np.cross(normals, x)
    sin = np.linalg.norm(axis, axis=1)
    cos = normals @ x
    # Rodrigues with k = axis / sin: R = I + [axis]x + [axis]x^2 (1 - cos) / sin^2
    skew = np.zeros((len(normals), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -axis[:, 2], axis[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = axis[:, 2], -axis[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = -axis[:, 1], axis[:, 0]
    factor = np.where(sin > 1e-9, (1.0 - cos) / np.maximum(sin, 1e-9) ** 2, 0.5)
    rotation = np.eye(3) + skew + factor[:, None, None] * skew @ skew
    flipped = cos < -1.0 + 1e-9  # normal along -x: turn half a revolution about z
    rotation[flipped] = np.diag([-1.0, -1.0, 1.0])
    transform = np.tile(np.eye(4), (len(normals), 1, 1))
    transform[:, :3, :3] = rotation
    transform[:, :3, 3] = -np.einsum("nij,nj->ni", rotation, points)
    return transform


def _angle_about_x(transform: FloatArray, points: FloatArray) -> FloatArray:
    """Angle [N] of each transformed point about the x axis (atan2(z, y))."""
    moved = np.einsum("nij,nj->ni", transform[:, :3, :3], points) + transform[:, :3, 3]
    return np.arctan2(moved[:, 2], moved[:, 1])


def align_pairs(
    model_p1: FloatArray,
    model_n1: FloatArray,
    model_p2: FloatArray,
    scene_p1: FloatArray,
    scene_n1: FloatArray,
    scene_p2: FloatArray,
) -> FloatArray:
    """Poses world_from_object [N, 4, 4] taking each model pair (p1 with normal n1, p2) onto the
    scene pair: p1 onto p1, n1 onto n1, and p2 onto the half-plane of the scene's p2 (exact
    when the features are equal). All inputs [N, 3]."""
    t_model = frame_to_x(model_p1, model_n1)
    t_scene = frame_to_x(scene_p1, scene_n1)
    alpha = _angle_about_x(t_scene, scene_p2) - _angle_about_x(t_model, model_p2)
    c, s = np.cos(alpha), np.sin(alpha)
    spin = np.zeros((len(alpha), 3, 3))
    spin[:, 0, 0] = 1.0
    spin[:, 1, 1], spin[:, 1, 2], spin[:, 2, 1], spin[:, 2, 2] = c, -s, s, c
    # t_scene = [R | -R p1] is rigid: its inverse is [R^T | p1], no general inverse needed
    scene_back = t_scene[:, :3, :3].transpose(0, 2, 1) @ spin  # [N, 3, 3]
    pose = np.tile(np.eye(4), (len(alpha), 1, 1))
    pose[:, :3, :3] = scene_back @ t_model[:, :3, :3]
    pose[:, :3, 3] = np.einsum("nij,nj->ni", scene_back, t_model[:, :3, 3]) + scene_p1
    return pose
