"""``stop``: stop every arm and gripper of the skill."""

from __future__ import annotations

from py_trees.common import Status
from vistac.tree import SkillBehaviour


class Stop(SkillBehaviour):
    """Stops all motion (the scheduler does the same on every exit path)."""

    def update(self) -> Status:
        errors = self.run.stop_motion()
        if errors:
            self.feedback_message = "; ".join(errors)
            return Status.FAILURE
        return Status.SUCCESS
