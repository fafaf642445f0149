"""csf_jax: the Conditional Score-based Filter (Zeng, Gan, Chen, Shi) in JAX/Flax.

Entry points:
  ``csf_jax.run(method, obs, ensemble, *, model=..., key=...)``: any filter, built as a ``Method``
    by ``csf_jax.methods`` (``methods.csf(...)``, ``methods.enkf()``, ...; ``methods.REGISTRY``
    by name, ``methods.build(name, **settings)``). The named functions below are conveniences
    over it.
  ``csf_jax.filter(trained, obs, ensemble, *, model=..., key=...)``: the CSF online stage
    (``trained``: a ``TrainedPrior``, the checked route; raw params; or None for the exact prior);
    settings ``CSFConfig``: ``SamplerConfig`` (with ``GuidanceConfig``), ``InflationConfig``,
    ``PriorConfig`` (with ``MixtureConfig``, and ``CovarianceConfig``: sample, Ledoit-Wolf shrunk
    or localised covariance for small ensembles). ``CSFConfig()`` is the filter for a model of
    one's own (the mixture prior); ``csf_jax.PAPER`` the paper's (the learned prior alone).
  ``csf_jax.simulate(problem, key)``: truth and observations of a ``StateSpaceModel``.
  ``csf_jax.problems.get(name)``: the paper's problems, Lorenz-96 and the zoo of unseen models.
  ``csf_jax.load_pretrained(name)``: the shipped trained prior of a problem.
  ``csf_jax.train_prior(model, key)``: train a prior for any ``StateSpaceModel``; ``.save(path)``,
    ``csf_jax.load_prior(path, model)``.
  ``csf_jax.score_filter``: the SF baseline (a score net trained online at every step).
  ``csf_jax.particle_filter`` / ``csf_jax.ensemble_kalman_filter`` / ``csf_jax.kalman_filter``.
  ``csf_jax.letkf``: the localised ensemble transform Kalman filter (Lorenz-96's baseline); its
    geometry ``ring_localization`` / ``Localization``.
  ``csf_jax.ensf``: the ensemble score filter (EnSF; training-free Monte-Carlo score, damped
    likelihood), a baseline; ``ENSFConfig``.
  ``csf_jax.ienks``: the local iterative ensemble Kalman smoother with a lag of one step
    (Gauss-Newton, localised as the LETKF), the local filters' iterative baseline; ``IEnKSConfig``.
  ``csf_jax.sharded_letkf``: the LETKF with its sites split over the devices of a mesh (several
    GPUs or hosts; docs/scale_out.md); ``csf_jax.sharded_transform_filter`` the same for the
    transform-form local CSF; ``site_mesh`` makes the mesh, ``gather_result`` brings a result's
    global arrays to every process.
  ``csf_jax.local_filter``: the local CSF, linear in d (a sparse Gaussian prior from local
    regressions, a probability-flow sampler); ``LocalCSFConfig``.
  ``csf_jax.local_transform_filter``: the local CSF in the LETKF's ensemble space (the LETKF
    with a linear sensor; a Levenberg-Marquardt mode and a per-member flow with a nonlinear one);
    ``LocalTransformConfig``.
  ``csf_jax.reference_filter``: the near-exact per-coordinate filter of the tables' reference row.
  ``csf_jax.gaussian_prior()`` / ``exact_mixture_prior()`` / ``learned_prior(network)``: CSF's
    prior-score sources (``filter(..., prior=)``).
  ``csf_jax.metrics``: error metrics; ``csf_jax.rmse`` the paper's RMSE.
  ``csf_jax.fit(build, theta0, obs, ensemble, key=...)``: a model's parameters by maximum
    likelihood (the filters' log evidence); ``csf_jax.ParametricModel(build, theta)``: a model
    whose numbers are traced (``jax.grad``, ``jax.vmap`` over them, one compilation);
    ``csf_jax.positive`` its constraint.
"""

# _threads first: one OpenBLAS thread for jaxlib's LAPACK kernels (see csf_jax._threads)
from csf_jax import _threads, methods, metrics, problems  # noqa: F401
from csf_jax.covariance import CovarianceConfig
from csf_jax.filters import (
                             CSFConfig,
                             ENSFConfig,
                             FilterResult,
                             IEnKSConfig,
                             LETKFConfig,
                             LocalCSFConfig,
                             Localization,
                             LocalTransformConfig,
                             ReferenceConfig,
                             SFConfig,
                             ensemble_kalman_filter,
                             ensf,
                             ienks,
                             kalman_filter,
                             letkf,
                             local_filter,
                             local_transform_filter,
                             particle_filter,
                             reference_filter,
                             ring_localization,
                             score_filter,
)
from csf_jax.filters.csf import PAPER, SamplerConfig
from csf_jax.filters.csf import csf_filter as filter  # noqa: A001  (the user-facing name)
from csf_jax.filters.driver import Method, run
from csf_jax.filters.sharded import gather_result, sharded_letkf, site_mesh
from csf_jax.filters.sharded_transform import sharded_transform_filter
from csf_jax.fit import FitResult, Transform, fit, positive
from csf_jax.guidance import GuidanceConfig
from csf_jax.inflation import InflationConfig
from csf_jax.metrics import rmse
from csf_jax.mixture import MixtureConfig
from csf_jax.networks import NetworkConfig, init_params
from csf_jax.parametric import ParametricModel
from csf_jax.pretrained import load_pretrained
from csf_jax.prior import (
                             PriorConfig,
                             PriorScore,
                             exact_mixture_prior,
                             gaussian_prior,
                             learned_prior,
)
from csf_jax.ssm import (
                             Likelihood,
                             ObservationNoise,
                             ProcessNoise,
                             StateSpaceModel,
                             Step,
                             cauchy_noise,
                             drop_observations,
                             gaussian_noise,
                             gaussian_noise_cov,
                             gaussian_process_noise,
                             log_likelihood,
                             poisson_likelihood,
                             propagate,
                             shock_steps,
                             simulate,
                             volatility_likelihood,
)
from csf_jax.trained import TrainedPrior, load_prior
from csf_jax.trained import deprecated_alias as _deprecated_alias
from csf_jax.training import DatasetConfig, TrainConfig, train_prior

__version__ = "0.7.0"

__all__ = ["CSFConfig", "FilterResult", "GuidanceConfig", "Likelihood", "MixtureConfig",
           "NetworkConfig", "ObservationNoise", "PAPER", "Step", "poisson_likelihood",
           "volatility_likelihood",
           "PriorScore", "ProcessNoise", "TrainedPrior", "DatasetConfig", "TrainConfig",
           "load_prior", "train_prior", "LETKFConfig", "LocalCSFConfig", "Localization", "letkf",
           "local_filter", "ring_localization", "ReferenceConfig", "SFConfig",
           "StateSpaceModel", "cauchy_noise", "drop_observations", "ensemble_kalman_filter",
           "exact_mixture_prior", "filter", "gaussian_noise", "gaussian_noise_cov",
           "gaussian_process_noise", "gaussian_prior", "init_params", "kalman_filter",
           "learned_prior", "load_pretrained", "log_likelihood", "metrics", "particle_filter", "problems",
           "propagate", "reference_filter", "rmse", "score_filter", "shock_steps", "simulate",
           "sharded_letkf", "sharded_transform_filter", "site_mesh", "gather_result", "ensf",
           "ENSFConfig", "ienks", "IEnKSConfig",
           "local_transform_filter", "LocalTransformConfig", "CovarianceConfig", "Method", "run",
           "methods", "SamplerConfig", "InflationConfig", "PriorConfig", "ParametricModel",
           "fit", "FitResult", "Transform", "positive"]


def __getattr__(name: str):
    """Deprecated names, with a ``DeprecationWarning``: ``csf_jax.Pretrained`` (``TrainedPrior``)
    and ``csf_jax.ROBUST`` (the mixture prior, which ``CSFConfig()`` has by default)."""
    if name == "ROBUST":
        import warnings

        warnings.warn("csf_jax.ROBUST is deprecated: the mixture prior is CSFConfig()'s default "
                      "(with particle kernels and the effective-sample-size discount), and "
                      "csf_jax.ROBUST returns CSFConfig(); the name goes in the next version",
                      DeprecationWarning, stacklevel=2)
        return CSFConfig()
    return _deprecated_alias(__name__, name)
