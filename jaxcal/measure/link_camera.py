"""A camera on one link of a tree reading a marker on another ("link_camera", alias "head_camera"): a head
camera watching a marker on the gripper of a mobile manipulator, y = C^-1 T_0^-1 T_1 m (3,). T_0 is the frame
of the camera's link (`robot.tips[0]`), T_1 that of the marker's link (`robot.tips[1]`), both moved by the
robot; C is the camera's frame on its link (`cam.x .y .z .rx .ry .rz`, zero: the link frame is the camera's
optical frame) and m the marker on its link (`tool.x .y .z`). The reading is the marker in the camera frame,
so the shared links below both (torso, base) cancel out of it except through their joints' motions.

No world frame is registered at the start (the camera rides on the robot): name the optical frame's link
as tips[0] so that C starts near zero, or give C's nominal values (`with_values`)."""

from __future__ import annotations

from jaxcal.kin.pose import Pose
from jaxcal.measure.base import XYZ, frame_from_params, frame_names
from jaxcal.measure.position import Position
from jaxcal.measure.registry import register


class LinkCamera(Position):
    """A marker on tips[1] read in a camera on tips[0]: a point reading like `Position` (residual, errors, noise),
    with no device frame in the world to register."""

    kind = "link_camera"
    frame_index = None
    marker_reading = None

    @classmethod
    def build(cls) -> "LinkCamera":
        return cls.nominal_device(frame_names("cam") + frame_names("tool", XYZ), (3,))

    @property
    def n_points(self) -> int:
        return 0

    def check_robot(self, robot) -> None:
        """The robot must be a tree read at two bodies: the camera's link, then the marker's."""
        if len(robot.tips) != 2:
            raise ValueError(f"link_camera reads a marker on one link in a camera on another: load robot {robot.name!r} "
                             "with tips=[camera link, marker link] (it has "
                             f"{len(robot.tips) or 1} tool frame{'s' if len(robot.tips) > 1 else ''})")

    def read(self, tip, d):
        """y = C^-1 T_0^-1 T_1 m, with C = frame(d[0:6]), m = d[6:9] and tip the stacked frames (T_0, T_1)."""
        camera_link = Pose(tip.R[0], tip.p[0])
        marker_link = Pose(tip.R[1], tip.p[1])
        return frame_from_params(d[0:6]).inverse().apply(camera_link.inverse().apply(marker_link.apply(d[6:9])))

    def points(self, y):
        return None


register(LinkCamera, "head_camera")
