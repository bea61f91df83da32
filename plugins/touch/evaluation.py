"""Touch metrics for the run summary: class right, pose error (TWD, eq. 46) and steps."""

from __future__ import annotations

from typing import Any

POSE_TOLERANCE_FRACTION = 0.1
"""A pose counts as found when its TWD is below this fraction of the object size."""


def touch_errors(touch: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    """From the ``touch`` summary (with its per-touch ``history``) and the probe's truth:
    class_correct, pose_error_m (last), steps_to_pose (first touch whose MLE class is right
    and whose pose error is under 10% of the object size, or None), steps (touches taken),
    contacts, max_particle_count."""
    history = touch.get("history") or []
    tolerance_m = POSE_TOLERANCE_FRACTION * float(truth["size_m"])
    steps_to_pose = next(
        (
            entry["touch"]
            for entry in history
            if entry.get("mle_class") == truth["class"]
            and entry.get("pose_error_m") is not None
            and entry["pose_error_m"] < tolerance_m
        ),
        None,
    )
    last = history[-1] if history else {}
    return {
        "class_correct": touch.get("mle_class") == truth["class"],
        "pose_error_m": last.get("pose_error_m"),
        "pose_tolerance_m": tolerance_m,
        "steps_to_pose": steps_to_pose,
        "steps": touch.get("touches", len(history)),
        "contacts": len(touch.get("contacts") or []),
        "max_particle_count": touch.get("max_particle_count"),
        "known": touch.get("known"),
        "stopped_by": touch.get("stopped_by"),
    }
