"""PNG figures of the main job, like the paper's (they need matplotlib: ``pip install matplotlib``).

* ``estimates.png``: filtered means of every method against the truth over time, run 0, for chosen
  coordinates (paper Figs. 2c/d, 4, 5); dotted lines mark the shocks.
* ``rmse_over_time.png``: RMSE over the runs at every filter step, per method (paper Fig. 6).
* ``prior.png`` (1-D problems): the propagated prior ensemble at one step against samples of CSF's
  prior for it, drawn by the filter's own sampler without the observation and without prior
  inflation (paper Fig. 2b).

Every method has its own colour, line style and marker; the truth is a thin dashed black line
drawn beneath them; legends sit outside the axes.
"""

from __future__ import annotations

import dataclasses
import os

import jax
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from csf_jax.filters.csf import (  # noqa: E402
    _prior_for,
    ancestral_sample,
    posterior_sample,
    sampler_start,
    uses_kalman,
)
from csf_jax.inflation import InflationConfig  # noqa: E402
from csf_jax.ssm import propagate  # noqa: E402

STYLES = {"CSF": dict(color="tab:red", ls="-", marker="o"),
          "CSF-G": dict(color="tab:orange", ls="--", marker="s"),
          "SF": dict(color="tab:blue", ls="-.", marker="^"),
          "EnKF": dict(color="tab:green", ls=(0, (5, 1.5)), marker="v"),
          "PF": dict(color="tab:purple", ls=":", marker="D"),
          "Ref.": dict(color="tab:cyan", ls="-", marker="x")}
TRUTH = dict(color="black", ls="--", lw=0.9, zorder=1)
COLORS = {m: s["color"] for m, s in STYLES.items()}
LABELS = {"CSF": "CSF", "CSF-G": "CSF, Gaussian prior", "SF": "SF", "EnKF": "EnKF", "PF": "PF",
          "Ref.": "reference"}


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
        ax.axvline(k + 1, color="gray", ls=":", lw=1, zorder=0)


def _style(method: str, index: int, points: int) -> dict:
    """Line keywords of the ``index``-th method: its colour, line style and marker, the markers
    spaced about a twelfth of the steps apart and offset per method so that they do not sit on
    each other; the first method (CSF) drawn on top."""
    every = max(1, points // 12)
    return dict(STYLES[method], lw=1.3, ms=4, markevery=(index * every // 6 % every, every),
                zorder=20 - index)


def estimates(out: str, name: str, truth, shocks, means: dict, run: int = 0) -> str:
    """Truth ``(R, K+1, d)`` against ``means[method] (R_m, K, d)`` for ``run``; returns the path."""
    dims = plotted_dims(truth.shape[-1])
    fig, axes = plt.subplots(len(dims), 1, figsize=(9, 2.4 * len(dims)), sharex=True, squeeze=False,
                             layout="constrained")
    steps = np.arange(truth.shape[1])
    for ax, i in zip(axes[:, 0], dims):
        ax.plot(steps, truth[run, :, i], label="truth", **TRUTH)
        for j, (m, mean) in enumerate(means.items()):
            if mean.shape[0] > run:
                ax.plot(steps[1:], mean[run, :, i], label=LABELS[m],
                        **_style(m, j, mean.shape[1]))
        _shock_lines(ax, shocks[run])
        ax.set_ylabel(f"x{i + 1}")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right upper", fontsize=8)
    axes[0, 0].set_title(f"{name}: estimates against the truth (run {run}; dotted: shocks)")
    axes[-1, 0].set_xlabel("filter step k")
    return _save(fig, out, "estimates.png")


def rmse_over_time(out: str, name: str, truth, shocks, means: dict) -> str:
    """RMSE over runs at each step, ``sqrt(mean_r |mean - truth|^2)``, per method."""
    fig, ax = plt.subplots(figsize=(9, 3.4), layout="constrained")
    for j, (m, mean) in enumerate(means.items()):
        err = np.sum((mean - truth[: mean.shape[0], 1:]) ** 2, axis=-1)
        ax.plot(np.arange(1, err.shape[1] + 1), np.sqrt(err.mean(axis=0)),
                label=f"{LABELS[m]} ({mean.shape[0]} runs)", **_style(m, j, err.shape[1]))
    ax.set_yscale("log")
    ax.set_xlabel("filter step k")
    ax.set_ylabel("RMSE over runs")
    ax.set_title(f"{name}: RMSE over time (every run has its own shock times)")
    fig.legend(loc="outside right upper", fontsize=8)
    return _save(fig, out, "rmse_over_time.png")


def prior_data(model, pretrained, config, ensemble0, key, shocks, prior=None) -> dict:
    """What ``prior.png`` plots, 1-D: the particle filter on one run (``key``: its simulation key,
    ``shocks`` its shock flags) up to the first shock (else the middle), then at that filter step
    the propagated prior ensemble and samples of CSF's prior for it. The particle filter, not CSF,
    gives the ensemble: before the first shock it is as accurate (the main job's table), and its
    run compiles in a second, where a CSF run of another length compiles its step again (7 s of
    the main job on a 2-core CPU).

    The samples come from the filter's own sampler (``config``'s: ancestral with Kalman guidance,
    or Euler-Maruyama for a DPS mode) started as in the filter, with the observation switched off
    (guide 0) and no prior inflation: what CSF's prior alone draws at that step. ``prior``: CSF's
    ``PriorScore`` when not the pretrained or exact one (``--prior gaussian``).

    Returns ``{"step": k + 1 (1-based filter step), "prior_ensemble": (N,), "csf_samples": (N,),
    "bins": the histogram edges, "prior_name": str}``; the bins span both sample sets.
    """
    import csf_jax

    K = shocks.shape[0]
    k = int(np.argmax(shocks)) if shocks.any() else K // 2
    k = max(k, 1)
    k_filt, k_prop, k_init, k_rev = jax.random.split(jax.random.fold_in(key, 7), 4)
    params = None if pretrained is None else pretrained.params
    network = None if pretrained is None else pretrained.network
    _, obs = csf_jax.simulate(model, key)
    source = _prior_for(params, prior, network, config)
    result = csf_jax.run(csf_jax.methods.pf(), obs[:k], ensemble0, model=model, key=k_filt,
                         return_ensembles=True)
    own = dataclasses.replace(config, inflation=InflationConfig(base=0.0, adaptive=False))

    @jax.jit  # one program: op by op, each of the encoder's and sampler's ops compiles alone
    def prior_and_samples(params, post, y):
        prior_ens = propagate(model, k_prop, post)
        centers = jax.vmap(model.drift)(post)
        context = source.condition(params, centers, prior_ens, model.process_std)
        x_init, start = sampler_start(own, prior_ens, k_init)
        if uses_kalman(own):
            return prior_ens, ancestral_sample(params, source, context, model, y, x_init, start,
                                               k_rev, own, 0.0)
        return prior_ens, posterior_sample(params, source, context, lambda x0: 0.0, x_init, k_rev,
                                           own, 0.0, start.tau)

    prior_ens, samples = prior_and_samples(params, result.ensembles[-1], obs[k])
    a, g = np.asarray(prior_ens[:, 0]), np.asarray(samples[:, 0])
    bins = np.linspace(min(a.min(), g.min()), max(a.max(), g.max()), 50)
    return {"step": k + 1, "prior_ensemble": a, "csf_samples": g, "bins": bins,
            "prior_name": source.name}


def prior_figure(out: str, name: str, data: dict) -> str:
    """Plot ``prior_data``'s output to ``prior.png``; returns the path."""
    fig, ax = plt.subplots(figsize=(7.5, 3.4), layout="constrained")
    ax.hist(data["prior_ensemble"], bins=data["bins"], density=True, color="0.6", alpha=0.6,
            label="prior ensemble")
    ax.hist(data["csf_samples"], bins=data["bins"], density=True, histtype="step", lw=1.8,
            color=COLORS["CSF"], label=f"CSF samples\n({data['prior_name']} prior)")
    ax.set_title(f"{name}: prior at filter step {data['step']} of run 0, from a PF run on its data")
    ax.set_xlabel("x")
    ax.set_ylabel("density")
    fig.legend(loc="outside right upper", fontsize=8)
    return _save(fig, out, "prior.png")


def prior_vs_model(out: str, name: str, model, pretrained, config, ensemble0, key, shocks,
                   prior=None) -> str:
    """``prior.png`` of one run (``prior_data``, then ``prior_figure``); returns the path."""
    data = prior_data(model, pretrained, config, ensemble0, key, shocks, prior=prior)
    return prior_figure(out, name, data)


def _save(fig, out: str, filename: str) -> str:
    path = os.path.join(out, filename)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
