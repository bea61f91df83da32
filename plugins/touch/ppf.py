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


def rotation_to_x(normals: FloatArray) -> FloatArray:
    """Rotations [N, 3, 3] turning each normal [N, 3] onto +x (Rodrigues about normal x +x;
    half a revolution about z for a normal along -x)."""
    nx, ny, nz = normals.T
    sin_squared = ny * ny + nz * nz
    # R = I + [a]x + [a]x^2 (1 - cos) / sin^2 with a = n x (1, 0, 0) = (0, nz, -ny)
    factor = np.where(sin_squared > 1e-18, (1.0 - nx) / np.maximum(sin_squared, 1e-18), 0.5)
    rotation = np.empty((len(normals), 3, 3))
    rotation[:, 0] = np.stack([1.0 - factor * sin_squared, ny, nz], axis=1)
    rotation[:, 1] = np.stack([-ny, 1.0 - factor * ny * ny, -factor * ny * nz], axis=1)
    rotation[:, 2] = np.stack([-nz, -factor * ny * nz, 1.0 - factor * nz * nz], axis=1)
    rotation[nx < -1.0 + 1e-9] = np.diag([-1.0, -1.0, 1.0])
    return rotation


def _angle_about_x(rotation: FloatArray, offset: FloatArray) -> FloatArray:
    """Angle [N] about the x axis (atan2(z, y)) of each offset [N, 3] once rotated [N, 3, 3]."""
    moved = np.einsum("nij,nj->ni", rotation[:, 1:], offset)
    return np.arctan2(moved[:, 1], moved[:, 0])


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
    when the features are equal). All inputs [N, 3].

    Both pairs are moved to p1 at the origin with n1 along +x (rotations R_m, R_s), the model
    is turned about x by the angle alpha between the p2s, and the scene move is undone:
    rotation R_s^T R_x(alpha) R_m, translation scene_p1 - rotation model_p1."""
    model_rotation, scene_rotation = rotation_to_x(model_n1), rotation_to_x(scene_n1)
    alpha = _angle_about_x(scene_rotation, scene_p2 - scene_p1) - _angle_about_x(
        model_rotation, model_p2 - model_p1
    )
    cos, sin = np.cos(alpha)[:, None], np.sin(alpha)[:, None]
    turned = model_rotation.copy()  # R_x(alpha) R_m
    turned[:, 1] = cos * model_rotation[:, 1] - sin * model_rotation[:, 2]
    turned[:, 2] = sin * model_rotation[:, 1] + cos * model_rotation[:, 2]
    poses = np.zeros((len(alpha), 4, 4))
    poses[:, :3, :3] = scene_rotation.transpose(0, 2, 1) @ turned
    poses[:, :3, 3] = scene_p1 - np.einsum("nij,nj->ni", poses[:, :3, :3], model_p1)
    poses[:, 3, 3] = 1.0
    return poses
