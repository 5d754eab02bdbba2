"""Genetic-algorithm calibration and Monte Carlo loops (seed 000 ch. 5)."""

from jaxcal.ga.runner import GAResult, calibrate
from jaxcal.ga.core import GAOptions
from jaxcal.ga.fitness import pose_fitness, residual_fitness, rotation_spectral_distance

__all__ = ["GAOptions", "GAResult", "calibrate", "pose_fitness", "residual_fitness", "rotation_spectral_distance"]
