"""Built-in robots (`get`, `available`) and the table builders."""

from jaxcal.closure.delta import DeltaGeometry
from jaxcal.robots.build import mcpc_robot, mdh_robot, pry_robot
from jaxcal.robots.builtin import available, get, register
from jaxcal.robots.delta_builder import delta_robot
from jaxcal.robots.hexapod import hexapod_from_radii, hexapod_robot
from jaxcal.robots.io import RobotFileError, load_robot, robot_from_dict, robot_to_dict, save_robot

__all__ = ["DeltaGeometry", "RobotFileError", "available", "delta_robot", "get", "hexapod_from_radii", "hexapod_robot", "load_robot",
           "mcpc_robot", "mdh_robot", "pry_robot", "register", "robot_from_dict", "robot_to_dict", "save_robot"]
