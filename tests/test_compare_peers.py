"""scripts/compare_peers.py: our GICP on raw scans, scored and saved."""

import json
import sys

import numpy as np
import pytest
from repo_scripts import import_script


@pytest.fixture(scope="module")
def compare_peers():
    return import_script("compare_peers")


def test_raw_scans_hide_the_point_times(compare_peers, sim_sequence):
    from gloam_jax import io

    seq = io.KittiSequence(sim_sequence, "00")
    assert seq.point_times(3) is not None  # the simulator wrote them
    raw = compare_peers.RawScans(seq)
    assert raw.point_times(3) is None
    np.testing.assert_array_equal(raw.scan(3), seq.scan(3))
    assert (raw.root, raw.sequence, raw.scan_path(3)) == (seq.root, seq.sequence,
                                                         seq.scan_path(3))  # fmt: skip


def test_our_gicp_runs_on_raw_scans_and_is_scored(compare_peers, sim_sequence, tmp_path,
                                                  monkeypatch):  # fmt: skip
    out = tmp_path / "peers"
    argv = f"compare_peers.py {sim_sequence} --sequences 00 --frames 8 --methods gicp --out {out}"
    monkeypatch.setattr(sys, "argv", argv.split())
    compare_peers.main()
    saved = json.loads(out.with_suffix(".json").read_text())
    scored = saved["results"]["00/gicp"]
    # 8 frames of a simulated drive: GICP follows it to within a few per cent of the path
    assert 0 <= scored["t_err"] < 5.0
    assert scored["median_ms_per_frame"] > 0
    assert saved["devkit"] is False
    assert saved["machine"]["cpu"] and saved["machine"]["jax_backend"] == "cpu"
    assert "00" in out.with_suffix(".md").read_text()


@pytest.mark.parametrize(
    "methods, variant, message",
    [
        ("gicp,smal_gicp", [], "unknown method 'smal_gicp'"),
        ("gicp,kiss-icp", [], "kiss-icp: its package is not installed"),
        ("gicp", ["--variant", "small_gicp={max_keyframes: 5}"], "--variant 'small_gicp'"),
    ],
)
def test_a_method_that_cannot_run_stops_before_any_run(compare_peers, sim_sequence, tmp_path,
                                                       monkeypatch, capsys, methods, variant,
                                                       message):  # fmt: skip
    """A sitting over several drives takes hours: a misspelt method, a peer whose package is
    missing or a variant named like a method is named at the start, not where it comes."""
    kiss = compare_peers.PEERS["kiss-icp"]
    monkeypatch.setitem(compare_peers.PEERS, "kiss-icp", kiss._replace(module="no_such_package"))
    out = tmp_path / "peers"
    argv = ["compare_peers.py", str(sim_sequence), "--sequences", "00", "--frames", "8",
            "--methods", methods, *variant, "--out", str(out)]  # fmt: skip
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit):
        compare_peers.main()
    assert message in capsys.readouterr().err
    assert not out.with_suffix(".json").exists()  # nothing ran
