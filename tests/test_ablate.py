"""experiments.ablate: settings are parsed and checked; a tiny ablation runs end to end."""

import argparse

import pytest

from experiments import ablate


def test_parse_setting():
    assert ablate.parse_setting("reverse_steps=20,prior_inflation=0.2") == {
        "reverse_steps": 20, "prior_inflation": 0.2}
    assert ablate.parse_setting("adaptive_inflation=True") == {"adaptive_inflation": True}
    assert ablate.parse_setting("guidance.proposals=4,reverse_steps=5") == {
        "guidance.proposals": 4, "reverse_steps": 5}
    cfg = ablate.make_config({"guidance.proposals": 4, "reverse_steps": 5})
    assert cfg.guidance.proposals == 4 and cfg.reverse_steps == 5 and cfg.guidance.mode == "kalman"
    for bad in ("steps=20", "reverse_steps", "reverse_steps=x y", "reverse_steps=1",
                "guidance.proposals=0", "guidance.nothing=1"):
        with pytest.raises(argparse.ArgumentTypeError):
            ablate.parse_setting(bad)


@pytest.mark.slow  # kept out of the default run's time budget; run with -m slow
def test_tiny_ablation_rows(tmp_path):
    rows = ablate.ablate("double_well", 1, [{"reverse_steps": 3},
                                            {"reverse_steps": 3, "adaptive_inflation": True}],
                         particles=64)
    assert [r["setting"] for r in rows] == [
        "EnKF", "CSF reverse_steps=3", "CSF reverse_steps=3, adaptive_inflation=True"]
    assert all(0.0 < r["rmse"] < 5.0 for r in rows)
    assert rows[0]["config"] is None and rows[2]["config"]["adaptive_inflation"] is True
    assert "| double_well | EnKF |" in ablate.table(rows, header=True)
    path = tmp_path / "rows.json"
    path.write_text(__import__("json").dumps({"rows": rows + rows[:1]}))
    assert ablate.render(str(path)).count("| double_well | EnKF |") == 1
    with pytest.raises(SystemExit):
        ablate.main([])
