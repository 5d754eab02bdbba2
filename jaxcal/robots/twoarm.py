"""A synthetic two-arm torso (a tree read at both hands): torso yaw and pitch carrying two 3-joint arms, with
URDF inertials (link masses 1.5-6 kg, centres of mass 0.12 m below each link frame).

The test robot for trees: a humanoid's arms share the torso, a marker on each hand is read by one tracker in the
same sample, and gravity loads the torso joints with the mass of both arms (issue 17 item 3). Built as URDF text,
so it goes through the same reader as a real robot's file."""

from __future__ import annotations

TIPS = ("left_hand", "right_hand")


def _joint(name, parent, child, xyz, rpy="0 0 0", kind="revolute", axis="0 0 1"):
    limit = "<limit lower='-2.5' upper='2.5' effort='10' velocity='1'/>" if kind == "revolute" else ""
    ax = f"<axis xyz='{axis}'/>" if kind == "revolute" else ""
    return (f"<joint name='{name}' type='{kind}'><parent link='{parent}'/><child link='{child}'/>"
            f"<origin xyz='{xyz}' rpy='{rpy}'/>{ax}{limit}</joint>")


def _link(name, mass):
    """A link, with a centre of mass 0.12 m below its frame of `mass` kg when mass > 0."""
    if not mass:
        return f"<link name='{name}'/>"
    return (f"<link name='{name}'><inertial><origin xyz='0 0 -0.12'/><mass value='{mass}'/>"
            "<inertia ixx='0.01' iyy='0.01' izz='0.01' ixy='0' ixz='0' iyz='0'/></inertial></link>")


def _arm(side, sign):
    """Three revolute joints and a fixed tool link; the fixed mounting joint folds into the first."""
    j = [_joint(f"{side}_mount", "torso", f"{side}_base", f"0 {sign * 0.2} 0.4", kind="fixed"),
         _joint(f"{side}_1", f"{side}_base", f"{side}_1_link", "0 0 0.05", axis="0 1 0"),
         _joint(f"{side}_2", f"{side}_1_link", f"{side}_2_link", "0 0 -0.3", rpy="0.1 0 0", axis="1 0 0"),
         _joint(f"{side}_3", f"{side}_2_link", f"{side}_3_link", "0.02 0 -0.25", axis="0 1 0"),
         _joint(f"{side}_tool", f"{side}_3_link", f"{side}_hand", "0 0 -0.1", kind="fixed")]
    links = [(f"{side}_base", 0), (f"{side}_1_link", 2), (f"{side}_2_link", 3), (f"{side}_3_link", 1.5), (f"{side}_hand", 0)]
    return j, links


def two_arm_urdf() -> str:
    """URDF text of the robot 'twoarm': a torso (yaw, then pitch) carrying two 3-joint arms."""
    joints = [_joint("torso_yaw", "base_link", "pelvis", "0 0 0.8"),
              _joint("torso_pitch", "pelvis", "torso", "0 0 0.1", axis="0 1 0")]
    links = [("base_link", 0), ("pelvis", 0), ("torso", 6)]
    for side, sign in (("left", 1), ("right", -1)):
        j, ln = _arm(side, sign)
        joints += j
        links += ln
    body = "".join(_link(n, m) for n, m in links) + "".join(joints)
    return f"<?xml version='1.0'?><robot name='twoarm'>{body}</robot>"


__all__ = ["TIPS", "two_arm_urdf"]
