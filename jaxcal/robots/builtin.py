"""Built-in robots from the seeds."""

from __future__ import annotations

import functools
import os

import numpy as np

from jaxcal.robots.io import load_robot
from jaxcal.robots.real_datasets import DATA_DIR, REAL_DATASETS
from jaxcal.robots.urdf import load_urdf

_REGISTRY: dict = {}


def register(name: str):
    def deco(fn):
        _REGISTRY[name] = fn
        return fn

    return deco


def available() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY))


def get(name: str):
    """A built-in robot by name (see `available()`). Robots are immutable and cached."""
    try:
        factory = _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown robot {name!r}; built-ins: {', '.join(available())}") from None
    return factory()


def _data_file(name: str) -> str:
    return os.path.join(os.path.dirname(__file__), "data", name)


@register("mrr1")
@functools.cache
def mrr1():
    """MRR-1, the R-R-P modular robot of seed 000 Table 6.1 (18 module parameters).

    home = the Table 6.1 joint motions (30 deg, 60 deg, 0.2 m), where the nominal tip is
    p = (0.4330127, 0.65, 0.25) m, R = [[0,-1,0],[-1,0,0],[0,0,-1]] (Table 6.6).
    """
    return load_robot(_data_file("mrr1.yaml"))


@register("stanford")
@functools.cache
def stanford():
    """Stanford RRP3R manipulator of seed 001 Table 1 (43 parameters: theta0, r0, five per frame
    1..7 and the gains K1..K6)."""
    return load_robot(_data_file("stanford.yaml"))


# --- closed mechanisms: four-bars (seed 004 §2.5, Table 4.2a) -------------------------------------

@register("fourbar2d")
@functools.cache
def fourbar2d():
    """The 2-D four-bar of seed 004 §2.5 (Figure 2.4, eq 2.71-2.87) in the thesis' own parameters.

    a = (a1..a6, phi1..phi6): link lengths and angle offsets, absolute joint angles; joint 1 is the
    actuator theta1, joints 4 and 5 are free, the loop closes (position only) between joints 2 and 6,
    and the tool is frame 5. The start (theta4, theta5) = (1.93, 3.32) selects the assembly mode of
    eq 2.87 (at theta1 = pi/2 + 0.4 the closure gives theta4 = 1.92697, theta5 = 3.31575).
    """
    from jaxcal.closure import Closure, planar_robot

    closure = Closure(pairs=((2, 6, "position"),), free=(4, 5), start=(1.93, 3.32))
    return planar_robot("fourbar2d", lengths=[0.95, 0.0, 0.9, 1.1, 0.9, 0.0], offsets=[0.0] * 6,
                        predecessors=[0, 1, 0, 3, 4, 5], actuated=(1,), closure=closure, tip=5,
                        home=[np.pi / 2 + 0.4], q_min=[np.pi / 2 - 0.6], q_max=[np.pi / 2 + 1.2])


# Table 4.2b of seed 004: the thesis' perturbed 3-D four-bar (rows a1 a2 a3 d1 d2 d3 of bodies 1..6), the
# "true" geometry of its simulations (used by tests/test_closure_3d.py and benchmarks/montecarlo_fourbar3d.py).
FOURBAR3D_TABLE_4_2B = (
    (0.0095, 0.0046, 0.0020, 0.0092, 0.0041, 0.0000),
    (0.0023, 0.0002, 0.0000, 0.0074, 1.0089, 0.0000),
    (0.0061, 0.0082, 0.0000, 1.0018, 0.0006, 0.0000),
    (-1.5659, 0.0044, 0.0000, 0.0041, 0.0035, 0.0000),
    (1.5797, 0.0062, 0.0000, 0.0094, 1.0081, 0.0000),
    (-1.5632, 0.0079, 0.0000, -0.9908, 0.0001, 0.0060),
)


@register("fourbar3d")
@functools.cache
def fourbar3d():
    """The 3-D four-bar of seed 004 Table 4.2a (Figure 4.11) as an MCPC tree with a ball-joint closure.

    Joint 1 actuated, joints 3-5 free (start 0, the closed configuration at theta1 = 0), closure
    (position) between frames 2 and 6, tool = frame 5. theta1 = +-pi/2 are the singular
    configurations (links stretched / joints 2 and 4 coincident), so q is kept within +-1.2 rad.
    """
    return load_robot(_data_file("fourbar3d.yaml"))


# -- Real robots (issue 8): the URDF chains of the built-in real datasets (`jaxcal.realdata`) --
def _real_robot(dataset: str):
    spec = REAL_DATASETS[dataset]
    return load_urdf(os.path.join(DATA_DIR, spec["folder"], spec["urdf"]), tip=spec["tip"], name=spec["robot"])


@register("talos_left_arm")
@functools.cache
def talos_left_arm():
    """PAL TALOS torso + left arm from its URDF (base_link -> gripper_left_base_link; 9 joints, 69
    parameters); data: `jaxcal.realdata.load("talos")`. URDF by FIGAROH's authors, Apache-2.0."""
    return _real_robot("talos")


@register("ur10")
@functools.cache
def ur10():
    """Universal Robots UR10 from its URDF (world -> wrist_3_link; 6 joints, 42 parameters);
    data: `jaxcal.realdata.load("ur10")`. URDF by FIGAROH's authors, Apache-2.0."""
    return _real_robot("ur10")


@register("tiago_arm")
@functools.cache
def tiago_arm():
    """PAL TIAGo torso lift + arm from its URDF (base_footprint -> wrist_ft_tool_link; 8 joints, 62
    parameters); data: `jaxcal.realdata.load("tiago")`. URDF by FIGAROH's authors, Apache-2.0."""
    return _real_robot("tiago")


@register("twoarm")
@functools.cache
def twoarm():
    """A synthetic torso with two 3-joint arms read at both hands (a tree: 8 joints, the torso shared;
    `jaxcal.robots.twoarm`), with URDF inertials for whole-tree gravity loads."""
    from jaxcal.robots.twoarm import TIPS, two_arm_urdf
    from jaxcal.robots.urdf import robot_from_urdf

    return robot_from_urdf(two_arm_urdf(), base="base_link", tips=list(TIPS), source="jaxcal.robots.twoarm")


# --- Delta and Kiwibot (seed 004 Tables 4.6 and 4.4) ---------------------------------------------

def free_list(name: str) -> list[str]:
    """The `free` list (parameter names) of a built-in robot's YAML table, e.g. "delta.yaml"."""
    import yaml

    with open(_data_file(name)) as fh:
        return yaml.safe_load(fh)["free"]


@register("delta")
@functools.cache
def delta():
    """The Canterbury Delta of seed 004 Table 4.6: 30 MCPC bodies, actuators 2-4 (theta1..3, rad,
    below the horizontal), five spherical closures, tool at the nacelle centre (body 30); 74 free
    parameters as marked in the table. Closure: nominal direct solution (§2.6) then Newton on the
    reduced square system (`jaxcal.closure.delta`)."""
    from jaxcal.closure.delta import with_delta_closure

    return with_delta_closure(load_robot(_data_file("delta.yaml")), free=free_list("delta.yaml"))


@register("kiwibot")
@functools.cache
def kiwibot():
    """The Kiwibot of seed 004 Table 4.4: 16 MCPC bodies, actuators 2-4, two spherical closures
    (15-13, 16-14), tool = nacelle frame 10; 39 free parameters as marked in the table. Each sample
    closes by the generic closure (Newton/LM hybrid) from the nominal homokinetic (mirror-mode)
    solution (`jaxcal.closure.kiwibot.closure_start`)."""
    from jaxcal.closure.kiwibot import with_kiwibot_closure

    return with_kiwibot_closure(load_robot(_data_file("kiwibot.yaml"))).with_free(free_list("kiwibot.yaml"))
