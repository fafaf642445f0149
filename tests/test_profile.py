"""``python -m experiments.profile``: its help runs, its stages compose to CSF's step (the same
posterior, timed positive) on a tiny case, and its block holds a table per route."""

import pathlib
import subprocess
import sys

import jax
import numpy as np

from experiments import profile

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_help_runs():
    done = subprocess.run([sys.executable, "-m", "experiments.profile", "--help"], cwd=ROOT,
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0 and "--page" in done.stdout, done.stderr[-2000:]


def test_stages_are_the_step_and_take_time():
    """d = 2 (the pendulum), N = 8, params=None: every stage times positive, and the stages fed
    one by one give the posterior of ``csf._step`` on the same inputs."""
    model, obs, ensemble, key = profile.case_data("pendulum", 8, 0, steps=3)
    bound, static, raw = profile.bind(model, None, ensemble)
    inp = profile.step_inputs(bound, static, raw, obs, ensemble, key, warm=1)
    stages, post, _ = profile.stage_pipeline(inp, repeats=1, budget=1.0)
    assert set(stages) == {"propagation", "moments", "ensemble_evidence", "particle_evidence",
                           "selection", "shock_draws", "transport"}
    assert all(t.seconds > 0 and t.calls == 1 for t in stages.values())
    (whole, _), _ = jax.jit(profile.whole_step(bound, static))(inp.params, inp.ens, inp.memory,
                                                               inp.y, inp.key, inp.k)
    np.testing.assert_allclose(np.asarray(post), np.asarray(whole), rtol=1e-5, atol=1e-6)


def test_trained_route_stages_are_the_step():
    """The double well's shipped prior, N = 64 (the sampler's block of 16 members): the stages
    give the step's posterior, and the network alone times positive."""
    model, obs, ensemble, key = profile.case_data("double_well", 64, 0, steps=3)
    bound, static, raw = profile.bind(model, profile.user_params("double_well", "trained"),
                                      ensemble)
    step = jax.jit(profile.whole_step(bound, static))
    inp = profile.step_inputs(bound, static, raw, obs, ensemble, key, warm=1, step=step)
    stages, post, _ = profile.stage_pipeline(inp, repeats=1, budget=1.0)
    assert "sampler" in stages and "transport" not in stages
    (whole, _), _ = step(inp.params, inp.ens, inp.memory, inp.y, inp.key, inp.k)
    np.testing.assert_allclose(np.asarray(post), np.asarray(whole), rtol=1e-5, atol=1e-6)
    assert profile.network_time(inp, stages["propagation"].output, 1, 1.0).seconds > 0


def test_block_has_a_table_per_route():
    def row(route, d, n):
        return {"route": route, "dim": d, "particles": n, "run_steps": 20,
                "stages_ms": {"propagation": 1.0, "transport" if route == "none" else "sampler":
                              6.0}, "stage_calls": {"propagation": 5}, "whole_step_ms": 10.0,
                "whole_step_calls": 3, "whole_step_compile_seconds": 2.5,
                "run_ms_per_step": 9.0, "members": {"particle": 40, "ensemble": 10, "shock": 0}}

    record = {"rows": [row("none", 1, 50), row("trained", 1, 50), row("trained", 10, 50)],
              "command": "python -m experiments.profile", "date": "2026-01-01", "warm_steps": 5,
              "machine": {"cpu": "a CPU", "cpu_count": 2, "jax_backend": "cpu"}}
    text = "\n".join(profile.page(record))
    assert text.count("| stage, ms (share of the whole step) |") == 2
    assert "| d = 1, N = 50 | d = 10, N = 50 |" in text
    assert "| propagation (drift + process noise, wild members dropped) | 1 (10%) |" in text
    assert "| other (whole step - stages) | 3 (30%) |" in text
    assert "| whole step's compile, s | 2.5 | 2.5 |" in text
    assert "| members drawn from the particle / ensemble / shock components | 40 / 10 / 0 |" \
        in text
    assert "median of 3-5 timed calls" in text
