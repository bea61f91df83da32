"""Image helpers shared by the real cameras."""

from __future__ import annotations

import numpy as np
from vistac.types import RGBD, PixelWindow


def resample(
    frame: RGBD, width: int | None, height: int | None, window: PixelWindow | None = None
) -> RGBD:
    """``frame`` cropped to ``window`` (if given), then resampled to ``width x height`` by
    nearest neighbour (depth is never interpolated across edges); unchanged when neither is
    given."""
    if window is not None:
        u0, v0, w, h = window.check(frame.intrinsics.width, frame.intrinsics.height)
        rows, cols = slice(v0, v0 + h), slice(u0, u0 + w)
        frame = RGBD(
            frame.depth_m[rows, cols], frame.intrinsics.cropped(window), frame.world_from_camera,
            frame.timestamp_s, None if frame.rgb is None else frame.rgb[rows, cols],
        )  # fmt: skip
    if width is None and height is None:
        return frame
    k = frame.intrinsics
    scaled = k.scaled(width or k.width, height or k.height)
    rows_px = np.minimum((np.arange(scaled.height) + 0.5) * k.height / scaled.height, k.height - 1)
    cols_px = np.minimum((np.arange(scaled.width) + 0.5) * k.width / scaled.width, k.width - 1)
    pick = np.ix_(rows_px.astype(int), cols_px.astype(int))
    rgb = frame.rgb[pick] if frame.rgb is not None else None
    return RGBD(frame.depth_m[pick], scaled, frame.world_from_camera, frame.timestamp_s, rgb)
