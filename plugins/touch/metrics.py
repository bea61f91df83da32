"""Hausdorff distances between point sets (paper 2, eq. 43 and 46)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from vistac.errors import DataError
from vistac.types import FloatArray


def nearest_distances(from_points: FloatArray, to_points: FloatArray) -> FloatArray:
    """For each point of ``from_points`` [N, 3], the distance [N] to its nearest point of
    ``to_points`` [M, 3]."""
    if len(to_points) == 0 or len(from_points) == 0:
        raise DataError("a Hausdorff distance needs two non-empty point sets")
    distance, _ = cKDTree(np.asarray(to_points)).query(np.asarray(from_points))
    return np.asarray(distance, dtype=np.float64)


def directed_hausdorff(a: FloatArray, b: FloatArray) -> float:
    """DHD(A, B) = max over a in A of the distance to the nearest b in B (eq. 43), in m."""
    return float(nearest_distances(a, b).max())


def two_way_hausdorff(a: FloatArray, b: FloatArray) -> float:
    """TWD(A, B) = max(DHD(A, B), DHD(B, A)) (eq. 46), in m."""
    return max(directed_hausdorff(a, b), directed_hausdorff(b, a))
