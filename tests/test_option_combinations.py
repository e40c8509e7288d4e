"""Options that contradict each other or the log, found by combining options: each is
refused or stated, not silently dropped."""

from __future__ import annotations

from pathlib import Path

import pytest

from tofloc import api
from tofloc.cli import main
from tofloc.errors import ParameterError


@pytest.fixture(scope="module")
def pillars(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log = tmp_path_factory.mktemp("pillars") / "pillars.h5"
    api.simulate("pillars", 1, out=log)
    return log


@pytest.mark.parametrize("mode", ["paper", "offset"])
def test_a_base_height_with_a_prior_centred_on_the_truth_is_refused(pillars: Path, mode: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """`--base-z 0.9` with the paper or offset prior on a log with truth was dropped (the
    estimates kept the truth's height, the JSON did not record 0.9); the global prior
    already refused it."""
    with pytest.raises(ParameterError, match=f"expected none with the {mode} prior"):
        api.localize_prior(pillars, mode=mode, base_z=0.9)
    assert main(["localize", str(pillars), "--estimator", "icp_pf", "--prior-mode", mode, "--base-z", "0.9"]) == 2
    assert "--base-z" in capsys.readouterr().err


@pytest.mark.parametrize("flag", ["--no-calibrate", "--calibrate"])
def test_paper_refuses_a_calibration_file_with_either_calibrate_flag(tmp_path: Path, flag: str,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """`paper --calibration X --no-calibrate` was accepted and X applied, although
    --no-calibrate promises the datasheet's model."""
    cal = tmp_path / "cal.toml"
    cal.write_text("")
    assert main(["paper", "--estimators", "icp_pf", "--calibration", str(cal), flag, "--out", str(tmp_path / "p")]) == 2
    assert "not both" in capsys.readouterr().err
    with pytest.raises(ParameterError, match="not both"):
        api.paper(["icp_pf"], out=tmp_path / "q", calibrate=False, calibration=cal)


def test_table_md_names_the_k_values_a_paper_run_used() -> None:
    """`paper --k-values 1,3`: table.md said "over k = 1..3 samples" and "the 3 per-k means"."""
    from evaluation.report import PAPER_TABLE_I, table_markdown

    doc = {"paper": PAPER_TABLE_I, "trials": 2, "seed": 0, "k_max": 3, "k_values": [1, 3], "results": {}, "comparisons": {}}
    table = table_markdown(doc)
    assert "over k in {1, 3} samples" in table and "of the 2 per-k means" in table
    table = table_markdown(dict(doc, k_values=[1, 2, 3]))
    assert "over k = 1..3 samples" in table and "of the 3 per-k means" in table
