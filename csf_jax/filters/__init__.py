"""Filters, each one jitted ``lax.scan`` over time returning a ``FilterResult``."""

from csf_jax.filters.csf import CSFConfig, csf_filter, posterior_sample
from csf_jax.filters.enkf import ensemble_kalman_filter
from csf_jax.filters.ensf import ENSFConfig, ensf
from csf_jax.filters.ienks import IEnKSConfig, ienks
from csf_jax.filters.kalman import kalman_filter
from csf_jax.filters.letkf import LETKFConfig, Localization, letkf, ring_localization
from csf_jax.filters.local_csf import LocalCSFConfig, local_filter
from csf_jax.filters.local_transform import LocalTransformConfig, local_transform_filter
from csf_jax.filters.pf import particle_filter, systematic_resample
from csf_jax.filters.reference import ReferenceConfig, reference_filter
from csf_jax.filters.result import FilterResult
from csf_jax.filters.sf import SFConfig, score_filter

__all__ = ["CSFConfig", "FilterResult", "LETKFConfig", "Localization", "csf_filter",
           "ensemble_kalman_filter", "ENSFConfig", "ensf", "IEnKSConfig", "ienks", "kalman_filter", "letkf", "LocalCSFConfig", "local_filter",
           "LocalTransformConfig", "local_transform_filter",
           "ring_localization",
           "particle_filter", "posterior_sample", "ReferenceConfig", "reference_filter",
           "score_filter", "SFConfig", "systematic_resample"]
