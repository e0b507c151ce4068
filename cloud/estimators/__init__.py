"""Estimators the aggregator feeds: each takes segments in and gives a snapshot out."""

from .base import Estimator
from .gmrf_profile import GmrfProfile
from .mean_profile import MeanProfile, ProfileSnapshot

__all__ = ["Estimator", "GmrfProfile", "MeanProfile", "ProfileSnapshot"]
