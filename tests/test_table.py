"""The results page generator (``experiments.table``): options, rendering, rewriting in place."""

import argparse
import copy
import os

import pytest

from experiments import table

RESULTS = os.path.join(os.path.dirname(__file__), "..", "results")


def test_parse_sf_runs():
    names = ["double_well", "cauchy"]
    assert table.parse_sf_runs(None, names) == {}
    assert table.parse_sf_runs("5", names) == {"double_well": 5, "cauchy": 5}
    assert table.parse_sf_runs("cubic20_corr=5, cauchy=3", names) == {"cubic20_corr": 5,
                                                                     "cauchy": 3}
    for bad in ("five", "nowhere=5", "cauchy=0", "cauchy=5=3"):
        with pytest.raises(argparse.ArgumentTypeError):
            table.parse_sf_runs(bad, names)


def test_render_marks_fewer_runs_and_missing_columns():
    results = table.load_results(RESULTS)
    assert "double_well" in results, "the committed results/ should hold the table's runs"
    one = {"double_well": copy.deepcopy(results["double_well"])}
    one["double_well"]["runs_used"]["sf"] = 5
    text = table.render(one, "cmd")
    sf_row = next(line for line in text.splitlines() if line.startswith("| SF |"))
    assert ", 5 runs)" in sf_row.split("|")[2]
    assert sf_row.split("|")[3].strip() == "- (0.176)"  # triple well not in ``one``
    assert "Made by `cmd`." in text


def test_write_page_replaces_only_the_generated_block(tmp_path):
    page = tmp_path / "r.md"
    page.write_text(f"# R\n\nintro\n{table.START}\nold\n{table.END}\n\nanalysis\n")
    table.write_page(str(page), "new")
    assert page.read_text() == f"# R\n\nintro\n{table.START}\nnew\n{table.END}\n\nanalysis\n"
    (tmp_path / "bad.md").write_text("no markers")
    with pytest.raises(SystemExit, match="markers"):
        table.write_page(str(tmp_path / "bad.md"), "x")


def test_render_reference_row_and_ratios():
    """The reference row carries no paper value and is never bold; the ratio table divides by it."""
    results = table.load_results(RESULTS)
    one = {"double_well": copy.deepcopy(results["double_well"])}
    res = one["double_well"]
    res["rmse"]["reference"] = 0.001  # below every method: still not the column's bold
    res["runs_used"]["reference"] = 10
    res["rmse_ratio"] = {m: v / 0.001 for m, v in res["rmse"].items()}
    text = table.render(one, "cmd").splitlines()
    ref = next(line for line in text if line.startswith("| Ref. |"))
    assert ref.split("|")[2].strip() == "0.0010"
    head = text.index("RMSE over the reference's RMSE on the same runs (1 is the best achievable):")
    csf = next(line for line in text[head:] if line.startswith("| CSF |"))
    assert csf.split("|")[2].strip() == f"{res['rmse']['csf'] / 0.001:.2f}"
    assert not any(line.startswith("| Ref. |") for line in text[head:head + 12])


def test_cache_fingerprint_ignores_fields_added_at_their_neutral_value():
    """A config field added later (``NetworkConfig.base``) must not invalidate the tables' cached
    runs at its neutral value, and must at any other."""
    from experiments import run
    old = {"sf": {"network": {"hidden": 64}}, "steps": [1, 2]}
    new = {"sf": {"network": {"hidden": 64, "base": "none"}}, "steps": (1, 2)}
    assert run._fingerprint(new) == run._fingerprint(old)
    other = {"sf": {"network": {"hidden": 64, "base": "gaussian"}}, "steps": [1, 2]}
    assert run._fingerprint(other) != run._fingerprint(old)


def test_config_differences_name_guidance_fields():
    """A column whose CSF config moves a ``GuidanceConfig`` field is listed with it (the Cauchy
    column's heavy-tailed proposals); a default config is not listed."""
    import dataclasses

    from experiments import run

    results = {name: {"config": {"csf": dataclasses.asdict(run.csf_config(name))}}
               for name in ("double_well", "cauchy")}
    assert table._config_differences(results) == [
        "cauchy: guidance.proposals=32, guidance.proposal_df=1"]
