"""Pose-target device ("pose_target", alias "fixture"): full-pose targets on a fixture, for
self-calibration from joint readings only (the variant at the end of seed 000 §7.4).

M targets (e.g. three-point targets) sit on a fixture; their poses X_i in the fixture frame were
established in advance, the fixture's pose W in the robot base frame is unknown. The robot matches its
tool frame to target i at joint readings q_i: F(q_i, a) = W X_i. One reading is the tool frame seen
from the fixture, y = W^-1 F(q) (4, 4), recorded as X_i; the residual is that of the pose device
(position difference, rotation vector of R_meas R_pred^T). The device parameters are W
(`dev.x .. dev.rz`); there is no marker frame (the tool frame is the one matched to the targets).

The fixture frame comes first in the base-set priority: relative poses cannot see the robot's base
frame, so the base-frame terms that W absorbs are the robot's (reported as not identifiable), not W's.
"""

from __future__ import annotations

import numpy as np

from jaxcal.measure.aim_line import TARGET_PRIORITY
from jaxcal.measure.base import FRAME_INDEX, frame_from_params, frame_names
from jaxcal.measure.pose import FullPose
from jaxcal.measure.registry import register


class PoseTarget(FullPose):
    """The tool frame read in the fixture frame W; W is the only parameter block."""

    kind = "pose_target"
    frame_index = FRAME_INDEX
    marker_reading = None  # d holds W only: clients that expect (frame, marker frame) must not take it for "pose"

    @classmethod
    def build(cls) -> "PoseTarget":
        return cls.nominal_device(frame_names("dev"), (4, 4))

    @property
    def priority(self) -> np.ndarray:
        return np.full(self.n_params, TARGET_PRIORITY)

    def read(self, tip, d):
        """Y = W^-1 T_tip with W = frame(d[0:6]), as a 4x4 matrix."""
        return frame_from_params(d[0:6]).inverse().compose(tip).matrix()


register(PoseTarget, "fixture")
