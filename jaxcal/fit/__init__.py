"""Identification: datasets, simulation, base parameters and the solvers."""

from jaxcal.fit import design, linear, uncertainty  # design: optimal configurations; linear: seed 000 ch. 4
from jaxcal.fit.base import BaseSet, base_set, regrouping_relations
from jaxcal.fit.data import DataError, Dataset
from jaxcal.fit.identify import FitResult, identify, residual_weights, residuals
from jaxcal.fit.simulate import perturb, random_configurations, simulate

__all__ = ["BaseSet", "DataError", "Dataset", "FitResult", "base_set", "identify", "perturb",
           "random_configurations", "regrouping_relations", "residual_weights", "residuals", "simulate", "uncertainty",
           "design", "linear"]
