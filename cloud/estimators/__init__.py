"""Estimators the aggregator feeds: each takes segments in and gives a snapshot out."""

from .base import Estimator
from .mean_profile import MeanProfile, ProfileSnapshot

__all__ = ["Estimator", "MeanProfile", "ProfileSnapshot"]
