"""Built-in robots (`get`, `available`) and the table builders."""

from jaxcal.robots.build import mcpc_robot, mdh_robot, pry_robot
from jaxcal.robots.builtin import available, get, register
from jaxcal.robots.io import RobotFileError, load_robot, robot_from_dict, robot_to_dict, save_robot

__all__ = ["RobotFileError", "available", "get", "load_robot", "mcpc_robot", "mdh_robot", "pry_robot",
           "register", "robot_from_dict", "robot_to_dict", "save_robot"]
