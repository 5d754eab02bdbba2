"""Measurement devices: one Device subclass per kind, each in its own module and registered by
name (`make_device`, `as_device`); the three-point orientation recovery and the theodolite location.

| kind             | reading (one sample)            | parameters                  | module         |
|------------------|---------------------------------|-----------------------------|----------------|
| "position"       | marker point, (3,)              | dev (6), tool point (3)     | position       |
| "multi_position" | K marker points, (K, 3)         | dev (6), tool points (3 K)  | multi_position |
| "pose"           | marker frame, (4, 4)            | dev (6), tool frame (6)     | pose           |
| "orientation"    | marker rotation, (3, 3)         | dev rotation (3), tool (3)  | orientation    |
| "three_point"    | three sphere centres, (3, 3)    | dev (6); spheres known      | three_point    |
| "theodolite"     | (azimuth, elevation) rad, (2,)  | dev (6), tool point (3)     | theodolite     |
| "laser_range"    | distance to the marker m, (1,)  | dev x y z (3), tool (3)     | laser_range    |
| "theodolite_range" | (azimuth, elevation, range), (3,) | dev (6), tool point (3)   | theodolite_range |
| "pose_target"    | tool frame in the fixture frame, (4, 4) | fixture frame (6)   | pose_target    |
| "aim_line"       | target offsets from a pointer's line, distances (3K + pairs,) | K targets (3 K) | aim_line |

A new kind is one module: subclass `jaxcal.measure.base.Device` and call `register(cls, *aliases)`.
"""

from jaxcal.measure import (  # noqa: F401  (each module registers its kind)
    aim_line,
    laser_range,
    multi_position,
    orientation,
    pose,
    pose_target,
    position,
    theodolite,
    theodolite_range,
    three_point,
)
from jaxcal.measure.base import Device, frame_from_params, key_normal
from jaxcal.measure.registry import as_device, device_class, make_device, register, registered_kinds
from jaxcal.measure.theodolite import locate_theodolite, sight_angles
from jaxcal.measure.three_point import three_point_orientation

__all__ = ["Device", "as_device", "device_class", "frame_from_params", "key_normal", "locate_theodolite", "make_device",
           "register", "registered_kinds", "sight_angles", "three_point_orientation"]
