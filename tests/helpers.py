"""The robots x devices test grid (issue 14): every built-in robot with every device it can drive.

`robot_device_grid` parametrises a test over (robot name, device kind) cells with ids such as
"ur10-theodolite". Cells outside `fast` are marked slow (run by `-m slow` / `make test-all`);
`covering` checks that a set of fast cells touches every device and every robot but SLOW_ROBOTS.
Robots, devices, configurations and device frames are cached per process, so tests of one module
share compiled functions.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

import jaxcal as jc

ROBOTS = ("mrr1", "stanford", "fourbar2d", "fourbar3d", "kiwibot", "delta", "talos_left_arm", "ur10", "tiago_arm")
DEVICES = ("position", "pose", "orientation", "three_point", "theodolite", "laser_range", "multi_position")

# Cells a robot cannot drive, with the reason; they are left out of the grid. None so far: the planar
# four-bar's tool pose is a full 3-D frame (motion in z = 0, rotation about z), which every device reads.
UNSUPPORTED: dict[tuple[str, str], str] = {}

# A generic device rotation (rotation vector, rad, |r| = 1.1) and device positions in the robot base frame (m).
DEVICE_ROTATION = (0.45, -0.6, 0.8)
DEVICE_POSITION = (1.2, -0.9, 0.6)  # 1.6 m from the base
THEODOLITE_POSITION = (2.6, 1.3, 0.5)  # 2.9 m: the instrument looks at the robot from a distance


# A two-joint URDF (revolute z then y, limits +-3 and +-2 rad): the valid input the bad-input tests break.
TWO_JOINT_URDF = """<robot name="two">
  <link name="base"/><link name="l1"/><link name="tool"/>
  <joint name="j1" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.2"/><axis xyz="0 0 1"/>
    <limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
  <joint name="j2" type="revolute"><parent link="l1"/><child link="tool"/><origin xyz="0.3 0 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
</robot>
"""

def cells():
    """Every supported (robot, device) pair, in grid order."""
    return [(r, d) for r in ROBOTS for d in DEVICES if (r, d) not in UNSUPPORTED]


# Robots left out of the default run, with the reason: their cheapest cell (the gradient check) took
# these times here; tests/test_kiwibot.py and tests/test_delta.py check their gradients by default.
SLOW_ROBOTS = {"kiwibot": "40 s a cell (loading, closure compile)", "delta": "95 s a cell (loading, closure compile)"}


def covering(fast):
    """The given cells, checked to include every device and every robot outside SLOW_ROBOTS."""
    fast = list(fast)
    _check_cells(set(fast))
    missing = (set(ROBOTS) - set(SLOW_ROBOTS) - {r for r, _ in fast}) | (set(DEVICES) - {d for _, d in fast})
    if missing:
        raise ValueError(f"the fast cells leave out {sorted(missing)}")
    return fast


def robot_device_grid(fast, xfail=None):
    """Parametrise a test over every grid cell as (robot_name, device_kind), ids "robot-device".

    fast: cells run by default (the others are marked slow).
    xfail: {cell: reason} for cells expected to fail today (strict, so a fix shows up as XPASS).
    """
    fast, xfail = set(fast), dict(xfail or {})
    _check_cells(fast | set(xfail))
    params = []
    for cell in cells():
        marks = [] if cell in fast else [pytest.mark.slow]
        if cell in xfail:
            marks.append(pytest.mark.xfail(strict=True, reason=xfail[cell]))
        params.append(pytest.param(*cell, id="-".join(cell), marks=marks))
    return pytest.mark.parametrize("robot_name,device_kind", params)


def _check_cells(given):
    bad = given - set(cells())
    if bad:
        raise ValueError(f"not grid cells: {sorted(bad)}")


def robot(name):
    """Built-in robot (cached by `jc.robots.get`)."""
    return jc.robots.get(name)


@functools.cache
def device(kind):
    """The device of a kind with nominal frames; multi_position reads two points."""
    return jc.make_device(kind, points=2 if kind == "multi_position" else None)


@functools.cache
def configurations(name, n, seed=0):
    """n joint vectors inside the robot's workspace (the Delta: its measurement cube)."""
    if name == "delta":
        from jaxcal.gap.closed import delta_workspace

        return delta_workspace(n, seed=seed)
    return jc.random_configurations(robot(name), n, seed=seed, margin=0.1)


@functools.cache
def device_frame(kind):
    """Device parameters (numpy): the frame rotated and away from the robot, marker offsets of a few
    centimetres; only the parameters the device has are set."""
    dev = device(kind)
    values = dict(zip(("dev.x", "dev.y", "dev.z"), THEODOLITE_POSITION if kind == "theodolite" else DEVICE_POSITION))
    values.update(zip(("dev.rx", "dev.ry", "dev.rz"), DEVICE_ROTATION))
    rng = np.random.default_rng(3)
    values.update({n: 0.03 * rng.standard_normal() for n in dev.names if n.startswith("tool.")})
    d = np.array(dev.nominal_np, float)
    for n, v in values.items():
        if n in dev.names:
            d[dev.names.index(n)] = v
    return d


def mcpc_spatial():
    """A four-body open MCPC chain in space (rows as `jaxcal.robots.mcpc_robot` takes them)."""
    from jaxcal.robots.build import mcpc_robot

    return mcpc_robot("spatial", [
        [0.1, -0.2, 0.3, 0.2, 0.1, 0.0, 0, 0, 0],
        [0.4, 0.1, 0.0, 0.3, -0.1, 0.0, 1, 0, 0],
        [-0.3, 0.2, 0.0, 0.0, 0.0, 0.1, 2, 0, 1],
        [0.2, 0.1, 0.5, 0.1, 0.2, 0.3, 3, 0, 3],
    ])
