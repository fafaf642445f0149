"""experiments.ablate: settings are parsed and checked; a tiny ablation runs end to end."""

import argparse

import pytest

from experiments import ablate


def test_parse_setting():
    assert ablate.parse_setting("reverse_steps=20,prior_inflation=0.2") == {
        "reverse_steps": 20, "prior_inflation": 0.2}
    assert ablate.parse_setting("adaptive_inflation=True") == {"adaptive_inflation": True}
    for bad in ("steps=20", "reverse_steps", "reverse_steps=x y", "reverse_steps=1"):
        with pytest.raises(argparse.ArgumentTypeError):
            ablate.parse_setting(bad)


def test_tiny_ablation_rows(tmp_path):
    rows = ablate.ablate("double_well", 1, [{"reverse_steps": 3},
                                            {"reverse_steps": 3, "adaptive_inflation": True}],
                         particles=64)
    assert [r["setting"] for r in rows] == [
        "EnKF", "CSF reverse_steps=3", "CSF reverse_steps=3, adaptive_inflation=True"]
    assert all(0.0 < r["rmse"] < 5.0 for r in rows)
    assert "| double_well | EnKF |" in ablate.table(rows, header=True)
    path = tmp_path / "rows.json"
    path.write_text(__import__("json").dumps({"rows": rows + rows[:1]}))
    assert ablate.render(str(path)).count("| double_well | EnKF |") == 1
    with pytest.raises(SystemExit):
        ablate.main([])
