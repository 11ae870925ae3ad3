"""experiments/invariant_features/probe_feature_shift.py: per-feature shifts in reference
standard deviations."""

import json
import sys

import numpy as np
import pytest
from repo_scripts import import_script

probe = import_script("probe_feature_shift", experiment="invariant_features")


def test_shifts_are_in_reference_standard_deviations():
    reference = np.array([[0.0, 5.0], [2.0, 5.0]])  # means (1, 5), stds (1, 0)
    compared = np.array([[3.0, 5.0], [3.0, 5.0]])
    np.testing.assert_allclose(probe.shifts(reference, compared), [2.0, 0.0])


def test_a_sequence_against_itself_shifts_nothing_and_the_cap_is_a_feature(
    sim_sequence, tmp_path, monkeypatch
):
    out = tmp_path / "shift"
    monkeypatch.setattr(sys, "argv", [
        "probe_feature_shift.py", str(sim_sequence), "--reference", "00", "--compare", "00",
        "--every", "20", "--options", "{drop: [density, intensity]}", "--out", str(out),
    ])  # fmt: skip
    probe.main()
    result = json.loads(out.with_suffix(".json").read_text())
    row = result["sequences"]["00"]
    assert len(row["features"]) == 18 and "density" not in row["features"]
    assert row["mean"] == pytest.approx(0.0, abs=1e-6)
    assert result["backbone"][1]["drop"] == ["density", "intensity"]
    assert "| 00 | 0.00 |" in out.with_suffix(".md").read_text()
    bad = ["--reference", "00", "--compare", "00", "--options", "[1]", "--out", str(out)]
    monkeypatch.setattr(sys, "argv", ["probe_feature_shift.py", str(sim_sequence), *bad])
    with pytest.raises(SystemExit, match="must be a YAML mapping"):
        probe.main()
