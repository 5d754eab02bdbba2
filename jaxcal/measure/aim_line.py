"""Aim-line device ("aim_line", alias "pointer"): a pointer (e.g. a laser) rigidly on the tool, aimed at
fixed targets, for self-calibration from joint readings only (seed 000 §7.4, eq 7.9-7.12).

The pointer leaves the tool at `offset` along `direction` (both in the tool frame, options of the
device, not parameters). Seed eq 7.10 treats it as a virtual prismatic joint of unknown extension
lambda whose tip is the target: o(q) + lambda u(q) = p_i, with o = T_tip offset and u = R_tip
direction. Eliminating lambda, an aim at target i says that the perpendicular offset of p_i from the
aim line is zero:

    e_i(q, a, p_i) = (I - u u^T)(p_i - o)                                         (3,)

and the known distances between targets (eq 7.9, 7.11) say |p_i - p_j| = d_ij. The device
parameters are the unknown target points p_1..p_K (`target1.x`, ...), estimated with the robot.

One reading (3 K + K (K - 1) / 2,) is what the pointer geometry shows at one tool pose: the offsets
e_1..e_K of every target from the aim line, then the distances |p_i - p_j| of the pairs i < j.
Recorded data fills in only what is known and leaves the rest NaN: an aim sample at target i has
e_i = 0 and NaN elsewhere (`aim_reading`), a distance sample has the known d_ij and NaN elsewhere
(`distance_reading`, any joint values). The residual is zero on NaN entries, so the stacked residual
over all samples is seed eq 7.12 with the nuisance extensions eliminated and the targets explicit.

The targets come first in the base-set priority (like the unknown plane coefficients of seed 001
eq 15): a target coordinate that the aims cannot fix (all aim lines at it parallel) then shows up as a
dependent device column instead of being silently absorbed by a robot parameter.
"""

from __future__ import annotations

import dataclasses
import itertools

import jax.numpy as jnp
import numpy as np

from jaxcal.measure.base import XYZ, Device, additive_noise, frame_names
from jaxcal.measure.registry import register

TARGET_PRIORITY = 10.0  # above every robot parameter (robot priorities are 0..~1): nuisance unknowns first


def target_pairs(k: int) -> tuple[tuple[int, int], ...]:
    """The pairs (i, j), i < j, of k targets in reading order."""
    return tuple(itertools.combinations(range(k), 2))


def perpendicular_offset(p, o, u):
    """(I - u u^T)(p - o): the offset of point p from the line through o along the unit vector u."""
    v = p - o
    return v - jnp.dot(v, u) * u


def safe_norm(v):
    """|v| with a finite derivative at v = 0 (two targets at the same start point)."""
    return jnp.sqrt(jnp.maximum(jnp.sum(v * v), 1e-300))


@dataclasses.dataclass(frozen=True, eq=False)
class AimLine(Device):
    """A pointer on the tool aimed at K fixed targets whose positions are the device parameters."""

    direction: tuple = (0.0, 0.0, 1.0)
    offset: tuple = (0.0, 0.0, 0.0)
    targets: int = 2

    kind = "aim_line"

    @property
    def residual_components(self) -> tuple[str, ...]:  # one length per reading entry
        return ("length",) * self.reading_shape[0]

    @classmethod
    def build(cls, targets: int = 2, direction=(0.0, 0.0, 1.0), offset=(0.0, 0.0, 0.0)) -> "AimLine":
        """K = `targets` >= 1 target points (all unknown, nominal 0); the pointer's unit `direction` and
        origin `offset` in the tool frame (default: along the tool z axis from the tool origin)."""
        u = np.asarray(direction, float).reshape(3)
        if not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-12:
            raise ValueError(f"direction must be a non-zero 3-vector, got {direction}")
        off = np.asarray(offset, float).reshape(3)
        k = int(targets)
        if k < 1:
            raise ValueError(f"targets must be >= 1, got {targets}")
        names = tuple(n for i in range(k) for n in frame_names(f"target{i + 1}", XYZ))
        shape = (3 * k + len(target_pairs(k)),)
        return cls.nominal_device(names, shape, direction=tuple(float(v) for v in u / np.linalg.norm(u)),
                                  offset=tuple(float(v) for v in off), targets=k)

    @property
    def priority(self) -> np.ndarray:
        return np.full(self.n_params, TARGET_PRIORITY)

    def line(self, tip):
        """(origin o, unit direction u) of the aim line at tool pose `tip` (robot base frame)."""
        return tip.apply(jnp.asarray(self.offset)), tip.R @ jnp.asarray(self.direction)

    def read(self, tip, d):
        """(e_1, ..., e_K, |p_i - p_j| for i < j): offsets of every target p_k = d[3k:3k+3] from the aim
        line, then the pairwise distances (eq 7.9-7.11)."""
        o, u = self.line(tip)
        P = d.reshape(self.targets, 3)
        offsets = jnp.stack([perpendicular_offset(P[k], o, u) for k in range(self.targets)]).reshape(-1)
        dists = [safe_norm(P[i] - P[j]) for i, j in target_pairs(self.targets)]
        return jnp.concatenate([offsets, jnp.stack(dists)]) if dists else offsets

    def residual(self, pred, meas):
        """meas - pred on the entries the sample knows, 0 on its NaN entries (3 K + pairs,)."""
        known = jnp.isfinite(meas)
        return jnp.where(known, meas, pred) - pred

    def split_errors(self, res):
        """(|residual| per sample, None)."""
        return jnp.linalg.norm(res, axis=-1), None

    def add_noise(self, y, normal, sigma_position, sigma_orientation):
        """y + sigma_position n on every entry (NaN entries stay NaN): the pointer's aim error and the
        error of the known distances."""
        return additive_noise(y, normal, sigma_position)

    # -- recorded data ------------------------------------------------------------------------------
    def aim_reading(self, target: int) -> np.ndarray:
        """The reading of an aim at target `target` (0-based): its offset 0, every other entry NaN."""
        y = np.full(self.reading_shape, np.nan)
        y[3 * target:3 * target + 3] = 0.0
        return y

    def distance_reading(self, distances: dict) -> np.ndarray:
        """The reading of the known distances {(i, j): d_ij} (0-based, i < j), every other entry NaN."""
        y = np.full(self.reading_shape, np.nan)
        pairs = target_pairs(self.targets)
        for (i, j), dij in distances.items():
            pair = (min(i, j), max(i, j))
            if pair not in pairs:
                raise ValueError(f"no target pair {pair} among {self.targets} targets")
            y[3 * self.targets + pairs.index(pair)] = float(dij)
        return y


register(AimLine, "pointer")
