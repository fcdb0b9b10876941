"""The demo command: runs, writes its figure and numbers, reaches the published accuracy."""

import json

import pytest

from ot_filter.cli import main


@pytest.mark.long
def test_demo_writes_outputs(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out)]) == 0
    assert (out / "demo.png").stat().st_size > 10_000
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["EnKF (square root, N=10)"]["rmse_a"] < 0.8
    assert metrics["SIR (regularised, N=800)"]["rmse_a"] < 0.4
    # The bimodal part: the OT filters hold both modes where the EnKF cannot and SIR collapses
    # (n = 10); W1 to the exact filter, with the N-sample floor about 0.04.
    bimodal = metrics["bimodal"]
    assert (out / "demo_bimodal.png").stat().st_size > 10_000
    assert bimodal["OT (localised)"]["w1"] < 0.5 * min(bimodal["EnKF"]["w1"], bimodal["SIR"]["w1"])
    assert bimodal["OT (global)"]["w1"] < bimodal["EnKF"]["w1"]
    assert "wrote" in capsys.readouterr().out


def test_demo_unwritable_output_is_a_one_line_error(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    assert main(["demo", "--out", str(blocker / "sub")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("ot-filter: error:") and error.count("\n") == 1
