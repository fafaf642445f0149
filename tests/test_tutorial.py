"""The tutorial page (docs/tutorial.md) runs as written: a model that is not built in, trained with
``train_prior``'s defaults, saved, loaded, filtered through gaps, compared and plotted. The page
itself asserts CSF's RMSE (``csf_jax.rmse``) is within 1.1x of the better of PF and EnKF. It runs
as a user runs it: with a user's XLA flags, and with a DeprecationWarning from its own code an
error. Its committed output (docs/tutorial/output.txt) names no folder of the machine that made it."""

import pathlib
import re

import pytest

from experiments import tutorial


@pytest.mark.slow
def test_the_tutorial_runs_and_csf_is_within_1_1x_of_the_best(tmp_path, monkeypatch):
    monkeypatch.setenv("PYTHONWARNINGS", "error::DeprecationWarning:__main__")
    out = tutorial.run(str(tmp_path))
    assert "refused:" in out and "observation map differs" in out
    rmse = {line.split(" RMSE")[0].strip(): float(line.split()[-1]) for line in out.splitlines()
            if " RMSE " in line}
    assert set(rmse) == {"CSF", "PF", "EnKF"}
    assert rmse["CSF"] <= 1.1 * min(rmse["PF"], rmse["EnKF"])
    assert (tmp_path / "lorenz63_tutorial.png").stat().st_size > 10_000
    assert (tmp_path / "lorenz63_prior" / "meta.json").exists()


def test_the_page_has_its_code():
    assert "CSF, paper" in tutorial.code(extras=True)
    assert "CSF, paper" not in tutorial.code()
    code = tutorial.code()
    for name in ("train_prior", "load_prior", ".save(", "drop_observations", "particle_filter",
                 "ensemble_kalman_filter", "savefig", "csf_jax.rmse("):
        assert name in code
    assert pathlib.Path(tutorial.PAGE).exists()


def test_the_committed_output_is_current_and_path_free():
    output = pathlib.Path(tutorial.PAGE).parent / "tutorial" / "output.txt"
    text = output.read_text()
    names = [line.split(" RMSE")[0].strip() for line in text.splitlines() if " RMSE " in line]
    assert names == ["CSF", "PF", "EnKF", "CSF, paper"], names
    assert "refused:" in text and "observation map differs" in text
    paths = re.findall(r"(?<![\w.])/(?:[\w.-]+/)+[\w.-]*", text)
    assert not paths, f"{output} names folders of the machine that made it: {paths}"
