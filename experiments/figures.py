"""PNG figures of the main job, like the paper's (needs matplotlib: ``pip install -e '.[plots]'``).

* ``estimates.png``: filtered means of every method against the truth over time, run 0, for chosen
  coordinates (paper Figs. 2c/d, 4, 5); dotted lines mark the shocks.
* ``rmse_over_time.png``: RMSE over the runs at every filter step, per method (paper Fig. 6).
* ``prior.png`` (1-D problems): the propagated prior ensemble at one step against samples of the
  CSF model's prior for it (the reverse SDE without guidance or prior inflation; paper Fig. 2b).
"""

from __future__ import annotations

import dataclasses
import os

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from csf_jax.filters.csf import (
    _prior_for,  # noqa: E402
    posterior_sample,  # noqa: E402
)
from csf_jax.sde import marginal_std  # noqa: E402
from csf_jax.ssm import propagate  # noqa: E402

COLORS = {"csf": "tab:red", "sf": "tab:blue", "enkf": "tab:green", "pf": "tab:purple",
          "reference": "black", "csf_gaussian": "tab:orange"}
LABELS = {"csf": "CSF", "csf_gaussian": "CSF, Gaussian prior", "sf": "SF", "enkf": "EnKF",
          "pf": "PF", "reference": "reference"}


def plotted_dims(dim: int) -> list[int]:
    """Coordinates shown: all up to 3; the paper's x1, x3, x5 for the 5-D Cauchy problem; else the
    first, middle and last."""
    if dim <= 3:
        return list(range(dim))
    if dim == 5:
        return [0, 2, 4]
    return [0, dim // 2, dim - 1]


def _shock_lines(ax, shocks) -> None:
    for k in np.nonzero(shocks)[0]:
        ax.axvline(k + 1, color="gray", ls=":", lw=1)


def estimates(out: str, name: str, truth, shocks, means: dict, run: int = 0) -> str:
    """Truth ``(R, K+1, d)`` against ``means[method] (R_m, K, d)`` for ``run``; returns the path."""
    dims = plotted_dims(truth.shape[-1])
    fig, axes = plt.subplots(len(dims), 1, figsize=(8, 2.4 * len(dims)), sharex=True, squeeze=False)
    steps = np.arange(truth.shape[1])
    for ax, i in zip(axes[:, 0], dims):
        ax.plot(steps, truth[run, :, i], color="black", lw=2, label="truth")
        for m, mean in means.items():
            if mean.shape[0] > run:
                ax.plot(steps[1:], mean[run, :, i], color=COLORS[m], lw=1.2, label=LABELS[m])
        _shock_lines(ax, shocks[run])
        ax.set_ylabel(f"x{i + 1}")
    axes[0, 0].legend(ncol=5, fontsize=8, loc="best", framealpha=0.6)
    axes[0, 0].set_title(f"{name}: estimates against the truth (run {run}; dotted: shocks)")
    axes[-1, 0].set_xlabel("filter step k")
    return _save(fig, out, "estimates.png")


def rmse_over_time(out: str, name: str, truth, shocks, means: dict) -> str:
    """RMSE over runs at each step, ``sqrt(mean_r |mean - truth|^2)``, per method."""
    fig, ax = plt.subplots(figsize=(8, 3.2))
    for m, mean in means.items():
        err = np.sum((mean - truth[: mean.shape[0], 1:]) ** 2, axis=-1)
        ax.plot(np.arange(1, err.shape[1] + 1), np.sqrt(err.mean(axis=0)), color=COLORS[m],
                label=f"{LABELS[m]} ({mean.shape[0]} runs)")
    ax.set_yscale("log")
    ax.set_xlabel("filter step k")
    ax.set_ylabel("RMSE over runs")
    ax.set_title(f"{name}: RMSE over time (every run has its own shock times)")
    ax.legend(fontsize=8)
    return _save(fig, out, "rmse_over_time.png")


def prior_vs_model(out: str, name: str, model, pretrained, config, ensemble0, key, shocks) -> str:
    """1-D: CSF on one run (``key``: its simulation key, ``shocks`` its shock flags) up to the first
    shock (else the middle), then the propagated prior ensemble against samples of the model's
    prior conditioned on it."""
    import csf_jax

    K = shocks.shape[0]
    k = int(np.argmax(shocks)) if shocks.any() else K // 2
    k = max(k, 1)
    k_filt, k_prop, k_init, k_rev = jax.random.split(jax.random.fold_in(key, 7), 4)
    params = None if pretrained is None else pretrained.params
    network = None if pretrained is None else pretrained.network
    _, obs = csf_jax.simulate(model, key)
    prior = _prior_for(params, None, network, config)
    result = csf_jax.filter(params, obs[:k], ensemble0, problem=model, key=k_filt, config=config,
                            network=network, return_ensembles=True)
    post = result.ensembles[-1]
    prior_ens = propagate(model, k_prop, post)
    centers = jax.vmap(model.drift)(post)
    context = prior.condition(params, centers, prior_ens, model.process_std)
    x_init = marginal_std(1.0, config.sigma_max) * jax.random.normal(k_init, prior_ens.shape)
    # the model's own prior: no inflation, no guidance
    generated = posterior_sample(params, prior, context, lambda x0: 0.0, x_init, k_rev,
                                 dataclasses.replace(config, prior_inflation=0.0), 0.0)
    fig, ax = plt.subplots(figsize=(6, 3.2))
    a, g = np.asarray(prior_ens[:, 0]), np.asarray(generated[:, 0])
    bins = np.linspace(min(a.min(), g.min()), max(a.max(), g.max()), 50)
    ax.hist(a, bins=bins, density=True, alpha=0.5, color="black", label="prior ensemble")
    ax.hist(g, bins=bins, density=True, histtype="step", lw=2, color=COLORS["csf"],
            label=f"CSF model ({prior.name} prior)")
    ax.set_title(f"{name}: prior at filter step {k + 1} of run 0, from a CSF run on its data")
    ax.set_xlabel("x")
    ax.legend(fontsize=8)
    return _save(fig, out, "prior.png")


def _save(fig, out: str, filename: str) -> str:
    path = os.path.join(out, filename)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
