"""Where the built-in real datasets live and which URDF chain and CSV columns each uses.

Shared by `jaxcal.robots.builtin` (the robots) and `jaxcal.realdata` (the measurements).
"""

import os

DATA_DIR = os.path.join(os.path.dirname(__file__), "data", "real")

REAL_DATASETS = {
    "talos": dict(robot="talos_left_arm", folder="talos", urdf="talos.urdf", csv="left_arm_mocap.csv", tip="gripper_left_base_link",
                  joints=("torso_1_joint", "torso_2_joint") + tuple(f"arm_left_{i}_joint" for i in range(1, 8)),
                  description="PAL TALOS humanoid, torso + left arm, motion-capture positions of one marker"),
    "ur10": dict(robot="ur10", folder="ur10", urdf="ur10.urdf", csv="calibration_pose.csv", tip="wrist_3_link",
                 joints=("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
                         "wrist_3_joint"),
                 description="Universal Robots UR10, full 6-D marker poses"),
    "tiago": dict(robot="tiago_arm", folder="tiago", urdf="tiago.urdf", csv="qualisys_static_postures.csv", tip="wrist_ft_tool_link",
                  joints=("torso_lift_joint",) + tuple(f"arm_{i}_joint" for i in range(1, 8)),
                  description="PAL TIAGo torso + arm, Qualisys motion capture of a rigid three-point marker"),
}
