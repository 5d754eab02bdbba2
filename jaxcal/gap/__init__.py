"""Sim-to-real gap diagnosis (issue 7): effect library, localisation, ranking, shrinkage.

    d = jc.gap.diagnose(robot, jc.Dataset(q=Q, y=Y, device="position", covariates={"time": T}))
    d.verdict, d.joints, d.ranking, d.shrink, d.where, d.report(), d.plot(folder), d.to_dict()
"""

from jaxcal.gap.diagnose import Candidate, Diagnosis, diagnose
from jaxcal.gap.effect import Effect, get_effect, register, registered_effects
from jaxcal.gap.effects import EFFECTS
from jaxcal.gap.model import GapModel, gap_model
from jaxcal.gap.simulate import effect_vector, simulate_effect

__all__ = ["EFFECTS", "Candidate", "Diagnosis", "Effect", "GapModel", "diagnose", "effect_vector", "gap_model", "get_effect",
           "register", "registered_effects", "simulate_effect"]
