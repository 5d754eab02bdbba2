"""Compatibility module: the device names as they were imported before each kind got its own
file (`from jaxcal.measure.devices import Device, make_device, ...`)."""

from __future__ import annotations

from jaxcal.kin.rotations import exp_so3, log_so3, skew  # noqa: F401  (imported from here by older code)
from jaxcal.measure import laser_range, link_camera, multi_position, orientation, pose, position, three_point  # noqa: F401  (register)
from jaxcal.measure.base import DEVICE_PRIORITY, Device, frame_from_params  # noqa: F401
from jaxcal.measure.registry import as_device, make_device
from jaxcal.measure.theodolite import locate_theodolite, sight_angles
from jaxcal.measure.three_point import three_point_orientation

__all__ = ["Device", "make_device", "as_device", "three_point_orientation", "frame_from_params", "locate_theodolite",
           "sight_angles", "skew"]
