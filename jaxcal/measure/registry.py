"""The registry of device kinds: name (and aliases) -> Device subclass; `make_device`, `as_device`."""

from __future__ import annotations

import inspect

from jaxcal.measure.base import Device

_CLASSES: dict[str, type[Device]] = {}  # kind name or alias -> class, in registration order
_ALIASES: dict[type[Device], tuple[str, ...]] = {}


def register(cls: type[Device], *aliases: str) -> type[Device]:
    """Make `cls` buildable by its `kind` and by each alias; returns cls."""
    for name in (cls.kind,) + aliases:
        old = _CLASSES.get(name)
        if old is not None and _where(old) != _where(cls):  # a module imported again may register again
            raise ValueError(f"device name {name!r} is already taken by {_where(old)}")
        _ALIASES.pop(old, None)
        _CLASSES[name] = cls
    _ALIASES[cls] = aliases
    return cls


def _where(cls) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def _expected() -> str:
    names = [c.kind + (f" ({', '.join(a)})" if a else "") for c, a in _ALIASES.items()]
    return ", ".join(names[:-1]) + " or " + names[-1]


def device_class(kind: str) -> type[Device]:
    """The Device subclass registered under `kind` (a kind name or an alias)."""
    cls = _CLASSES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ValueError(f"unknown device {kind!r}; expected {_expected()}")
    return cls


def registered_kinds() -> tuple[str, ...]:
    """The registered device kinds (without aliases), in registration order."""
    return tuple(c.kind for c in _ALIASES)


def _options(cls) -> tuple[str, ...]:
    return tuple(inspect.signature(cls.build).parameters)


def make_device(kind: str, **options) -> Device:
    """A device of the given kind (or alias) with nominal (identity) frames, all parameters
    unknown. Options go to the kind's `build`, e.g. `points=K` (multi_position), `targets=`
    (three_point); an option given as None is left out."""
    cls = device_class(kind)
    given = {k: v for k, v in options.items() if v is not None}
    for opt in given:
        if opt not in _options(cls):
            owners = sorted({c.kind for c in _ALIASES if opt in _options(c)})
            raise ValueError(f"{opt}= is for the {' / '.join(owners) or 'no'} device, not {cls.kind!r}")
    return cls.build(**given)


def as_device(device, y=None) -> Device:
    """A Device from a Device or a kind name; by name, the device that reads y when its options
    follow from the readings (multi_position: K points from y (N, K, 3))."""
    if isinstance(device, Device):
        return device
    return device_class(device).for_readings(y)
