"""Measurement devices (`make_device`) and the three-point orientation recovery."""

from jaxcal.measure.devices import Device, frame_from_params, make_device, three_point_orientation

__all__ = ["Device", "frame_from_params", "make_device", "three_point_orientation"]
