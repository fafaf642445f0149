"""The main job's figures draw what the filters computed: ``prior.png`` plots samples of CSF's own
prior at the figure's filter step (the filter's sampler, no observation, no inflation), so their
spread is the prior ensemble's, not that of a coarser sampler."""

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from csf_jax import CSFConfig, SamplerConfig  # noqa: E402
from experiments import figures, harness, run  # noqa: E402


def _prior_data(pretrained=None, steps=10):
    case = harness.Case("double_well", (("num_steps", 12),), runs=1, particles=256)
    data = harness.simulate(case)
    config = CSFConfig(sampler=SamplerConfig(reverse_steps=steps))
    return figures.prior_data(case.model, pretrained, config, data.ensembles[0],
                              harness.run_keys(0, [0])[0, 0], np.asarray(data.shocks[0]))


def _check_spread(data):
    prior, samples, bins = data["prior_ensemble"], data["csf_samples"], data["bins"]
    assert np.all(np.isfinite(samples)) and samples.shape == prior.shape
    mean, std = prior.mean(), prior.std()
    # the samples' spread is the prior ensemble's (params=None: the ensemble's Gaussian, its
    # moments, up to sampling noise), and the plotted range stays within a few of its stds
    assert 0.7 < samples.std() / std < 1.4, (samples.std(), std)
    assert abs(samples.mean() - mean) < 0.5 * std
    assert mean - 8 * std <= bins[0] and bins[-1] <= mean + 8 * std, (bins[0], bins[-1], mean, std)
    assert bins[0] <= min(prior.min(), samples.min()) and bins[-1] >= max(prior.max(),
                                                                          samples.max())


@pytest.mark.slow
def test_prior_figure_plots_the_filters_own_prior_samples(tmp_path):
    data = _prior_data()
    assert data["prior_name"] == "gaussian" and 1 <= data["step"] <= 12
    _check_spread(data)
    path = figures.prior_figure(str(tmp_path), "double_well", data)
    assert path.endswith("prior.png") and (tmp_path / "prior.png").stat().st_size > 5_000


def test_estimates_and_rmse_figures_are_written(tmp_path):
    rng = np.random.default_rng(0)
    truth = rng.standard_normal((2, 11, 1))
    shocks = np.zeros((2, 10), bool)
    shocks[0, 4] = True
    means = {m: truth[:, 1:] + 0.1 * rng.standard_normal((2, 10, 1)) for m in run.LABELS}
    for path in (figures.estimates(str(tmp_path), "x", truth, shocks, means),
                 figures.rmse_over_time(str(tmp_path), "x", truth, shocks, means)):
        assert (tmp_path / path.split("/")[-1]).stat().st_size > 5_000
    styles = {(s["color"], str(s["ls"]), s["marker"]) for s in figures.STYLES.values()}
    assert len(styles) == len(figures.STYLES)  # every method its own look
    assert len({s["color"] for s in figures.STYLES.values()}) == len(figures.STYLES)
    assert all(s["color"] != figures.TRUTH["color"] for s in figures.STYLES.values())
