"""The surgical robot in pybullet, its rod, and calibration sweeps. (Issue 7 fills this.)"""

from __future__ import annotations

from testbed.spec import Spec


class RobotSpec(Spec):
    """``[robot]``: the robot, its rod and its imperfections."""

    urdf: str = "builtin"
