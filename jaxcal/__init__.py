"""jaxcal: differentiable robot calibration in JAX.

    import jaxcal as jc
    rb = jc.robots.get("stanford")
    data = jc.simulate(rb, jc.perturb(rb, 1e-3), jc.random_configurations(rb, 100), "position", noise=1e-5)
    fit = jc.identify(rb, data)
"""

from jaxcal import (
           _setup,  # noqa: F401  (float64 before anything traces; compilation cache only on request)
           ga,  # noqa: E402  (genetic algorithm)
           gap,  # sim-to-real gap diagnosis
           measure,
           realdata,  # built-in real datasets (TALOS, UR10, TIAGo)
           robots,
)
from jaxcal._setup import enable_compilation_cache
from jaxcal.fit import DataError, Dataset, FitResult, identify, perturb, random_configurations, simulate, uncertainty
from jaxcal.fit.identifiable import identifiable
from jaxcal.fit.identify import apply_to_session
from jaxcal.forward import forward
from jaxcal.kin import Pose, Robot
from jaxcal.measure import make_device
from jaxcal.robots.io import load_robot, save_robot

__version__ = "0.1.0"
__all__ = ["DataError", "Dataset", "FitResult", "Pose", "Robot", "apply_to_session", "enable_compilation_cache", "forward",
           "ga", "gap", "identifiable", "identify", "make_device", "load_robot", "measure", "perturb", "random_configurations",
           "realdata", "robots", "save_robot", "simulate", "uncertainty"]
