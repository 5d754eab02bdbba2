"""Scale error of the device per axis: dv = s * v (elementwise)."""

from __future__ import annotations

from jaxcal.gap.effect import Effect


class DeviceScale(Effect):
    name = "device_scale"
    per_joint = False
    acts_on = frozenset({"reading"})
    terms = ("x", "y", "z")

    def reading_offset(self, theta, v, c):
        return v * theta

