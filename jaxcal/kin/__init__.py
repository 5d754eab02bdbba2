"""Kinematics: rotations, poses, joint conventions and the tree evaluator."""

from jaxcal.kin.model import Body, Robot, forward_open, frames, joint_variables
from jaxcal.kin.pose import Pose

__all__ = ["Body", "Pose", "Robot", "forward_open", "frames", "joint_variables"]
