"""`forward(robot, a, q)`: the tool frame, with loop closure solved inside for closed mechanisms."""

from __future__ import annotations

from jaxcal.closure.core import forward_closed
from jaxcal.kin.model import Robot, forward_open
from jaxcal.kin.pose import Pose


def forward(robot: Robot, a, q) -> Pose:
    """Tool pose for joint inputs q (..., n_inputs) and parameters a (n_params,)."""
    if robot.closure is not None:
        fast = getattr(robot.closure, "forward", None)  # a mechanism-specific closure (e.g. the Delta)
        if fast is not None:
            return fast(robot, a, q)
        return forward_closed(robot, a, q)
    return forward_open(robot, a, q)
