"""The maths of the built-in joint conventions, re-exported from their modules in `jaxcal.kin.joints`
(PRY modules, modified DH, MCPC, URDF joints, planar absolute-angle bodies); see
`jaxcal.kin.convention` for the interface and the registry."""

from jaxcal.kin.joints.mcpc import MCPC_ROW, mcpc_frame
from jaxcal.kin.joints.mdh import MDH_ROW, mdh_frame
from jaxcal.kin.joints.planar import PLANAR_ROW, planar_link
from jaxcal.kin.joints.pry import PRY_KINDS, PRY_ROW, pry_module, pry_motion
from jaxcal.kin.joints.urdf import URDF_ROW, URDF_TYPES, axis_rotation, rpy_to_matrix, urdf_joint

__all__ = ["MCPC_ROW", "MDH_ROW", "PLANAR_ROW", "PRY_KINDS", "PRY_ROW", "URDF_ROW", "URDF_TYPES", "axis_rotation",
           "mcpc_frame", "mdh_frame", "planar_link", "pry_module", "pry_motion", "rpy_to_matrix", "urdf_joint"]
