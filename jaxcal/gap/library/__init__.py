"""The built-in effects, one module each, registered here in the order of `BUILT_IN` (the order of `EFFECTS`,
hence of the ranking's ties and of the parameter layout)."""

from jaxcal.gap.effect import register
from jaxcal.gap.library import (
    backlash,
    compliance,
    coupling,
    device_bias,
    device_scale,
    drift,
    encoder_gain,
    gear,
    link_bending,
    payload,
    thermal,
)

BUILT_IN = (
    compliance.Compliance(),
    gear.Gear(),
    backlash.Backlash(),
    encoder_gain.EncoderGain(),
    coupling.Coupling(),
    thermal.Thermal(),
    drift.Drift(),
    device_scale.DeviceScale(),
    device_bias.DeviceBias(),
    link_bending.LinkBending(),
    payload.Payload(),
)
for _effect in BUILT_IN:
    register(_effect)
