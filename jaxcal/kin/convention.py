"""The joint-convention interface and its registry.

A convention says how one body's parameter row and joint values give the body's frame in its
parent's frame, T = local_transform(row, kind, qv), and answers the questions other modules ask
about a joint (is it prismatic, which axis does it move along, which row entry does its variable
offset). `Body.convention` names a registered convention; `Body.conv` is the object. A new
convention is one module in `jaxcal.kin.joints` (imported, hence registered, with the package) or,
outside the package, any subclass instance passed to `register`.
"""

from __future__ import annotations

import abc

import numpy as np

from jaxcal.kin.pose import Pose

Z_AXIS = (0.0, 0.0, 1.0)

_REGISTRY: dict[str, "Convention"] = {}


class Convention(abc.ABC):
    """One parametrisation of a body's local transform.

    Class attributes:
        name: registry key (the `Body.convention` string).
        row_names: names of the entries of one body's parameter row.
        kinds: the joint kinds it accepts (for kinds that carry data, such as a URDF axis, one
            example per joint type).
        file_format: "yaml" (seed-table robot file) or "urdf": how a calibrated robot is written.
        reads_parent: False for the usual parent-relative joints. True when joint angles are
            absolute (measured from the base): the evaluator then passes the parent's row and
            joint values in front of the body's own, local_transform(parent_row ++ row, kind,
            parent_qv ++ qv), zeros for a body on the base.
    """

    name: str
    row_names: tuple[str, ...]
    kinds: tuple
    file_format: str = "yaml"
    reads_parent: bool = False

    @abc.abstractmethod
    def local_transform(self, row, kind, qv) -> Pose:
        """The body's frame in its parent's frame for parameter row `row` and joint values `qv`."""

    @abc.abstractmethod
    def n_inputs(self, kind) -> int:
        """How many joint variables a body of this kind consumes."""

    @abc.abstractmethod
    def is_prismatic(self, kind) -> bool:
        """True when the (first) joint variable is a length along the joint axis."""

    @abc.abstractmethod
    def joint_row_index(self, kind) -> int | None:
        """Index in the row of the entry the (first) joint variable adds to; None for a fixed body."""

    def is_fixed(self, kind) -> bool:
        """True when the local transform takes no joint variable (a constant frame)."""
        return self.n_inputs(kind) == 0

    def is_revolute(self, kind) -> bool:
        """True when the (first) joint variable is an angle about the joint axis."""
        return not self.is_fixed(kind) and not self.is_prismatic(kind)

    def joint_axis(self, kind) -> np.ndarray:
        """Unit vector of the joint motion in the body's own frame (z unless the convention says otherwise)."""
        return np.array(Z_AXIS)

    def axis_through_parent_origin(self, kind) -> bool:
        """True when the joint axis passes through the parent's origin instead of the body's own."""
        return False


def register(convention: Convention) -> Convention:
    """Add a convention under `convention.name`; a name already taken by another class is an error."""
    known = _REGISTRY.get(convention.name)
    if known is not None and type(known) is not type(convention):
        raise ValueError(f"convention {convention.name!r} is already registered by {type(known).__name__}")
    _REGISTRY[convention.name] = convention
    return convention


def get_convention(name: str) -> Convention:
    """The registered convention called `name`."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValueError(f"unknown convention {name!r}; registered: {sorted(_REGISTRY)}") from None


def registered() -> tuple[str, ...]:
    """Names of every registered convention."""
    return tuple(sorted(_REGISTRY))
