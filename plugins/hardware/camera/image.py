"""Image helpers shared by the real cameras."""

from __future__ import annotations

import numpy as np
from vistac.types import RGBD


def resample(frame: RGBD, width: int | None, height: int | None) -> RGBD:
    """``frame`` resampled to ``width x height`` by nearest neighbour (depth is never
    interpolated across edges); unchanged when no size is given."""
    if width is None and height is None:
        return frame
    k = frame.intrinsics
    scaled = k.scaled(width or k.width, height or k.height)
    rows = np.minimum((np.arange(scaled.height) + 0.5) * k.height / scaled.height, k.height - 1)
    cols = np.minimum((np.arange(scaled.width) + 0.5) * k.width / scaled.width, k.width - 1)
    pick = np.ix_(rows.astype(int), cols.astype(int))
    rgb = frame.rgb[pick] if frame.rgb is not None else None
    return RGBD(frame.depth_m[pick], scaled, frame.world_from_camera, frame.timestamp_s, rgb)
