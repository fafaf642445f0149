"""The data's likelihood, measured: each filter's log evidence against a reference, a model
comparison by it, and parameters learned by ``csf_jax.fit``.

    python -m experiments.fitting [--out results/fitting] [--page docs/fitting.md]

Three blocks of docs/fitting.md, and its figure (docs/fitting.png with ``--page``):

* ``results:evidence``: the summed log evidence ``log p(y_1 .. y_K)`` of each filter against the
  exact value (the Kalman filter on a linear-Gaussian model) or a 10^6-particle filter's
  (``REFERENCE_PARTICLES``), over ``--runs`` simulated records of each model (``EVIDENCE``):
  the mean and the largest absolute difference.
* ``results:comparison``: the Cauchy problem's records filtered under its own noise and under a
  Gaussian noise of the same central interval (``ObservationNoise.gaussian_std``); the count of
  records whose evidence picks the Cauchy noise.
* ``results:fits``: ``csf_jax.fit`` on three models (``FITS``), each value fitted against its
  target (the exact maximum-likelihood value on a grid, or the truth), with the wall seconds of
  the whole fit (compilation included) on this machine. The figure: the Lorenz-96 forcing's log
  evidence over a grid of values (one compilation) and the fit's path.
"""

from __future__ import annotations

import dataclasses
import pathlib
import time
import warnings
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np

import csf_jax
from csf_jax.problems.linear import LinearGaussian, linear_gaussian, to_model
from csf_jax.problems.lorenz96 import obs_sites, rk4_step
from experiments import cli, harness, interrupt

REFERENCE_PARTICLES = 1_000_000
PARTICLES = 1000


@dataclasses.dataclass(frozen=True)
class Case:
    """A model whose evidence is measured: its name on the page, how to make it, the filters
    measured on it (``Method`` builders by label) and N."""

    label: str
    model: Callable
    filters: tuple
    particles: int = PARTICLES


def _linear():
    return linear_gaussian(5, 3, num_steps=50)


EVIDENCE = (
    Case("linear-Gaussian (d = 5, m = 3, K = 50)", _linear,
         (("EnKF", csf_jax.methods.enkf), ("PF", csf_jax.methods.pf),
          ("CSF", csf_jax.methods.csf)), 10_000),
    Case("pendulum (d = 2, K = 50)", lambda: csf_jax.problems.get("pendulum"),
         (("EnKF", csf_jax.methods.enkf), ("PF", csf_jax.methods.pf),
          ("CSF", csf_jax.methods.csf))),
    Case("double well without its shock (d = 1, K = 100)",
         lambda: csf_jax.problems.get("double_well", shock_count=0),
         (("EnKF", csf_jax.methods.enkf), ("PF", csf_jax.methods.pf),
          ("CSF", csf_jax.methods.csf))),
    Case("double well with its shock (d = 1, K = 100)",
         lambda: csf_jax.problems.get("double_well"),
         (("PF", csf_jax.methods.pf), ("CSF", csf_jax.methods.csf))),
)


def reference(model, obs, key) -> float:
    """The exact log-likelihood of a ``LinearGaussian``'s record (Kalman), else a
    ``REFERENCE_PARTICLES``-particle filter's (whose weights may collapse at a shock the model
    lacks: that is the model's own verdict, so the warning is silenced)."""
    if not isinstance(model, csf_jax.StateSpaceModel):
        return float(csf_jax.kalman_filter(obs, model=model).log_evidence.sum())
    ens = model.initial_ensemble(key, REFERENCE_PARTICLES)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(csf_jax.particle_filter(obs, ens, model=model, key=key,
                                             check_finite=False).log_evidence.sum())


def evidence_rows(runs: int, seed: int, progress: bool) -> list:
    """Per case and filter: the summed log evidence minus the reference's, over ``runs``."""
    rows = []
    for case in EVIDENCE:
        source = case.model()
        model = source if isinstance(source, csf_jax.StateSpaceModel) else to_model(source)
        diffs = {label: [] for label, _ in case.filters}
        refs, spread = [], []
        for run in range(runs):
            k_sim, k_ref, k_ens, k_run = jax.random.split(jax.random.key(seed + run), 4)
            _, obs = csf_jax.simulate(model, k_sim)
            refs.append(reference(source, obs, k_ref))
            spread.append(abs(reference(source, obs, jax.random.fold_in(k_ref, 1)) - refs[-1]))
            ens = model.initial_ensemble(k_ens, case.particles)
            for label, build in case.filters:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    result = csf_jax.run(build(), obs, ens, model=model, key=k_run,
                                         check_finite=False)
                diffs[label].append(float(result.log_evidence.sum()) - refs[-1])
        for label, values in diffs.items():
            rows.append({"case": case.label, "filter": label, "particles": case.particles,
                         "runs": runs, "reference_mean": float(np.mean(refs)),
                         "mean_difference": float(np.mean(values)),
                         "largest_difference": float(np.max(np.abs(values))),
                         "reference_spread": float(np.mean(spread))})
            if progress:
                print(f"{case.label}, {label}: {rows[-1]['mean_difference']:+.2f} nats",
                      flush=True)
    return rows


def comparison(runs: int, seed: int) -> dict:
    """The Cauchy problem's records under their own noise and a Gaussian one (module
    docstring), by the particle filter's evidence (N = 10,000)."""
    cauchy = csf_jax.problems.get("cauchy", num_steps=100)
    gaussian = cauchy._replace(name="cauchy_as_gaussian",
                               obs_noise=csf_jax.gaussian_noise(cauchy.obs_noise.gaussian_std))
    picked, gaps = 0, []
    for run in range(runs):
        k_sim, k_ens, k_run = jax.random.split(jax.random.key(seed + run), 3)
        _, obs = csf_jax.simulate(cauchy, k_sim)
        ens = cauchy.initial_ensemble(k_ens, 10_000)
        with warnings.catch_warnings():   # the Gaussian noise's weights collapse: expected
            warnings.simplefilter("ignore", RuntimeWarning)
            a, b = (float(csf_jax.particle_filter(obs, ens, model=m, key=k_run,
                                                  check_finite=False).log_evidence.sum())
                    for m in (cauchy, gaussian))
        picked += a > b
        gaps.append(a - b)
    return {"runs": runs, "picked_cauchy": int(picked), "smallest_gap": float(np.min(gaps)),
            "median_gap": float(np.median(gaps))}


def _linear_fit():
    """d = 1, 500 steps at q = 0.3, r = 0.5: (q, r) by the Kalman filter and the EnKF (N = 100)
    from a start 50% off, against the grid maximum of the exact log-likelihood."""
    lg = linear_gaussian(1, q_std=0.3, r_std=0.5, num_steps=500)
    base = to_model(lg)
    _, obs = csf_jax.simulate(base, jax.random.key(1))

    def build_linear(theta):
        return LinearGaussian(lg.A, lg.H, theta["q"], theta["r"], lg.m0, lg.p0_std,
                              lg.num_steps, lg.name)

    def build(theta):
        return base._replace(process_std=theta["q"],
                             obs_noise=csf_jax.gaussian_noise(theta["r"]))

    qs, rs = jnp.linspace(0.2, 0.45, 51), jnp.linspace(0.35, 0.65, 61)
    surface = jax.jit(jax.vmap(jax.vmap(lambda q, r: csf_jax.kalman_filter(
        obs, model=csf_jax.ParametricModel(build_linear, {"q": q, "r": r})).log_evidence.sum(),
        (None, 0)), (0, None)))(qs, rs)
    i, j = np.unravel_index(int(jnp.argmax(surface)), surface.shape)
    target = {"q": float(qs[i]), "r": float(rs[j])}
    rows = []
    start = {"q": 0.5, "r": 0.3}
    for label, fn, ens, method in (
            ("Kalman", build_linear, None, csf_jax.methods.kalman()),
            ("EnKF, N = 100", build, base.initial_ensemble(jax.random.key(2), 100), None)):
        t0 = time.perf_counter()
        fit = csf_jax.fit(fn, start, obs, ens, key=jax.random.key(0), method=method,
                          transform=csf_jax.positive(), progress=False)
        seconds = time.perf_counter() - t0
        for name in ("q", "r"):
            rows.append({"model": "linear-Gaussian, d = 1, K = 500", "filter": label,
                         "parameter": name, "fitted": float(fit.theta[name]),
                         "target": target[name], "target_is": "grid maximum of the likelihood",
                         "seconds": seconds})
    return rows


def _pendulum_fit():
    """The pendulum's observation std from 200 steps (truth 0.1), EnKF N = 200."""
    pendulum = csf_jax.problems.get("pendulum")
    _, obs = csf_jax.simulate(pendulum, jax.random.key(2), 200)

    def build(theta):
        return pendulum._replace(obs_noise=csf_jax.gaussian_noise(theta["r"]))

    t0 = time.perf_counter()
    fit = csf_jax.fit(build, {"r": 0.3}, obs, pendulum.initial_ensemble(jax.random.key(3), 200),
                      key=jax.random.key(0), steps=100, transform=csf_jax.positive(),
                      progress=False)
    return [{"model": "pendulum, K = 200", "filter": "EnKF, N = 200",
             "parameter": "observation std", "fitted": float(fit.theta["r"]), "target": 0.1,
             "target_is": "truth", "seconds": time.perf_counter() - t0}]


def _lorenz96_fit():
    """Lorenz-96's forcing (d = 40, every site seen, truth F = 8) from 200 steps by the LETKF
    (N = 20) from F = 6; and its log evidence over a grid of F, for the figure."""
    base = csf_jax.problems.get("lorenz96", num_steps=200, burn_in=0)
    h = csf_jax.problems.config("lorenz96").dt
    loc = csf_jax.ring_localization(base.dim, obs_sites(csf_jax.problems.config("lorenz96")))
    _, obs = csf_jax.simulate(base, jax.random.key(0))
    ens = base.initial_ensemble(jax.random.key(1), 20)
    method = csf_jax.methods.letkf(loc)

    def build(theta):
        return base._replace(drift=lambda x: rk4_step(x, h, theta["F"]))

    t0 = time.perf_counter()
    fit = csf_jax.fit(build, {"F": 6.0}, obs, ens, key=jax.random.key(2), method=method,
                      steps=100, learning_rate=0.1, progress=False)
    seconds = time.perf_counter() - t0
    grid = jnp.linspace(6.0, 10.0, 41)
    curve = jax.jit(jax.vmap(lambda f: csf_jax.run(
        method, obs, ens, model=csf_jax.ParametricModel(build, {"F": f}),
        key=jax.random.key(2), check_finite=False).log_evidence.sum()))(grid)
    row = {"model": "Lorenz-96, d = 40, K = 200", "filter": "LETKF, N = 20",
           "parameter": "forcing F", "fitted": float(fit.theta["F"]), "target": 8.0,
           "target_is": "truth", "seconds": seconds}
    figure = {"grid": np.asarray(grid).tolist(), "log_evidence": np.asarray(curve).tolist(),
              "path": np.asarray(fit.trace["F"]).tolist()}
    return [row], figure


def fit_rows(progress: bool):
    """The fits of ``FITS``, and the Lorenz-96 figure's data."""
    rows = []
    for fn in (_linear_fit, _pendulum_fit):
        rows += fn()
        if progress:
            print(f"fitted: {rows[-1]['model']}", flush=True)
    lorenz, figure = _lorenz96_fit()
    return rows + lorenz, figure


def fits_block(record: dict) -> list:
    rows = [[r["model"], r["filter"], r["parameter"], f"{r['fitted']:.3f}",
             f"{r['target']:.3f} ({r['target_is']})",
             f"{100 * (r['fitted'] / r['target'] - 1):+.1f}%", f"{r['seconds']:.0f}"]
            for r in record["fits"]]
    m = record["machine"]
    return harness.table(["model", "filter", "parameter", "fitted", "target", "off by",
                          "seconds"], rows) + [
        "", f"Made by `{record['command']}` on {record['date']}, {m['cpu']} ({m['cpu_count']} "
            f"cores); seconds: the whole `fit` call, compilation included."]


def figure(data: dict, path: str) -> None:
    """The Lorenz-96 forcing: the log evidence over the grid, and the fit's path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.2))
    left.plot(data["grid"], data["log_evidence"], color="C0")
    left.axvline(8.0, color="k", ls=":", label="truth")
    left.set(xlabel="forcing F", ylabel="log evidence (LETKF)")
    left.legend()
    right.plot(data["path"], color="C1", label="fit")
    right.axhline(8.0, color="k", ls=":", label="truth")
    right.set(xlabel="iteration", ylabel="F")
    right.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def evidence_block(record: dict) -> list:
    rows = [[r["case"], r["filter"], f"{r['particles']:,}", f"{r['reference_mean']:.2f}",
             f"{r['reference_spread']:.2f}", f"{r['mean_difference']:+.2f}",
             f"{r['largest_difference']:.2f}"]
            for r in record["rows"]]
    return harness.table(["model", "filter", "N", "reference", "its own error",
                          "mean difference", "largest |difference|"], rows) + [
        "", f"Made by `{record['command']}` on {record['date']}: {record['rows'][0]['runs']} "
            f"records per model, in nats; the reference is the Kalman filter's exact value for "
            f"the linear model and a {REFERENCE_PARTICLES:,}-particle filter's elsewhere, whose "
            f"own error is the mean gap between two of them with other keys on the same record."]


def comparison_block(record: dict) -> list:
    c = record["comparison"]
    return [f"The Cauchy noise is picked on {c['picked_cauchy']} of {c['runs']} records; the "
            f"log evidence of the Cauchy noise exceeds the Gaussian's by {c['smallest_gap']:.0f} "
            f"nats at least, {c['median_gap']:.0f} nats at the median (made by "
            f"`{record['command']}`)."]


def main(argv=None):
    p = harness.parser("fitting", "The filters' log evidence against a reference, and a model "
                       "comparison by it (docs/fitting.md).", cache=False)
    harness.add_outputs(p, "results/fitting", "docs/fitting.md")
    harness.add_sizes(p, runs=5, seed=0)
    args = p.parse_args(argv)
    cli.check_outputs(p, args, "evidence")
    t0 = time.perf_counter()
    rows = evidence_rows(args.runs, args.seed, not args.no_progress)
    fits, data = fit_rows(not args.no_progress)
    record = harness.results_record("fitting", harness.command("fitting", argv), rows,
                                    comparison=comparison(10, args.seed + 100), fits=fits,
                                    lorenz96=data)
    record["seconds"] = time.perf_counter() - t0
    harness.publish(args, record, evidence_block(record), tag="evidence")
    harness.publish(_no_out(args), record, comparison_block(record), tag="comparison")
    harness.publish(_no_out(args), record, fits_block(record), tag="fits")
    if args.page:
        figure(data, str(pathlib.Path(args.page).with_suffix(".png")))


def _no_out(args):
    """``args`` without ``--out``: the second block of the same record, written once."""
    import argparse

    return argparse.Namespace(**{**vars(args), "out": None})


if __name__ == "__main__":
    interrupt.main(main, "fitting")
