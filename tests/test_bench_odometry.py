"""scripts/bench_odometry.py: how a drive is scored, short or devkit-long."""

import numpy as np
import pytest
from repo_scripts import import_script


@pytest.fixture(scope="module")
def bench_odometry():
    return import_script("bench_odometry")


def _straight(n: int, step_m: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = step_m * np.arange(n)  # camera frame: forward is z
    return poses


@pytest.mark.parametrize("n, step_m", [(200, 0.1), (150, 1.0)])
def test_a_drive_is_scored_by_the_devkit_or_over_segments_scaled_to_it(bench_odometry, n, step_m):
    gt = _straight(n, step_m)
    est = _straight(n, 1.01 * step_m)  # 1 % too long everywhere
    scored = bench_odometry.score(gt, est)
    # A segment ends at the first frame past its length: up to one step long, over >= 2 m.
    assert scored["t_err_percent"] == pytest.approx(1.0, abs=0.06)
    assert scored["r_err_deg_per_100m"] == pytest.approx(0.0, abs=1e-6)
    if n * step_m < 100:  # 19.9 m: shorter than the devkit's 100 m, so 10-80 % of the path
        assert scored["lengths_m"] == [2, 4, 6, 8, 10, 12, 14, 16]
    else:
        assert "lengths_m" not in scored


def test_our_methods_get_a_per_stage_breakdown(bench_odometry, sim_sequence):
    from gloam_jax import io
    from gloam_jax.odometry import OdometryConfig
    from gloam_jax.timing import STAGES

    seq = io.KittiSequence(sim_sequence, "00")
    poses, ms, extra = bench_odometry.run_ours(
        seq, 5, OdometryConfig(), None, bench_odometry._CompileCounter()
    )
    assert poses.shape == (5, 4, 4) and len(ms) == 5
    assert 5 * extra["wall_ms_per_frame"] >= sum(ms)  # the loop holds every registration
    stages = extra["stage_ms"]
    assert tuple(stages) == STAGES
    assert all(0 <= s["median"] <= s["p95"] for s in stages.values())
    for stage in ("load", "voxels", "deskew", "neighbours", "covariances", "solve"):
        assert stages[stage]["median"] > 0, stage
    assert stages["features"]["p95"] == 0  # gicp: no backbone
    # registration's stages: their medians over frames 2-4 add up to no more than those
    # frames' registration time (a bound that holds whatever their spread), and to some of it
    registration = sum(
        s["median"] for k, s in stages.items() if k not in ("load", "features", "voxels")
    )
    assert min(ms[2:]) / 10 < registration <= sum(ms[2:]) + 0.1
    table = bench_odometry.stage_table({"00/gicp": {"stage_ms": stages}, "00/small_gicp": {}})
    header, rule, row = table.splitlines()
    assert header.split(" | ")[2:-1] == list(STAGES) and rule.count("---") == len(STAGES) + 3
    cells = row.strip("| ").split(" | ")
    assert cells[:2] == ["00", "gicp"] and len(cells) == len(STAGES) + 3
    assert cells[2] == f"{stages['load']['median']:.1f} / {stages['load']['p95']:.1f}"
    assert float(cells[-1]) == pytest.approx(sum(s["median"] for s in stages.values()), abs=0.06)


def test_isolated_runs_report_process_time_and_memory(bench_odometry, sim_sequence, tmp_path):
    """--isolate: each method in processes of its own, ours twice (empty, then filled
    compilation cache), a peer once, with their wall and CPU time; the table gives frame
    times, both runs and the cores the last one kept busy."""
    import json
    import os
    import subprocess
    import sys

    from repo_scripts import ROOT

    out = tmp_path / "bench.json"
    cmd = [sys.executable, str(ROOT / "scripts" / "bench_odometry.py"), str(sim_sequence),
           "--sequences", "00", "--frames", "4", "--methods", "gicp,small_gicp",
           "--isolate", "--out", str(out)]  # fmt: skip
    printed = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    results = json.loads(out.read_text())
    ours, peer = results["00/gicp"], results["00/small_gicp"]
    assert list(ours["process_s"]) == list(ours["peak_mib"]) == ["first", "cached"]
    assert list(ours["cpu_s"]) == ["first", "cached"]
    assert list(peer["process_s"]) == list(peer["cpu_s"]) == ["first"]
    for r in (ours, peer):
        assert all(v > 0 for v in r["process_s"].values())
        # CPU time of the child alone (user and system, all its threads), at most all cores
        for label, cpu in r["cpu_s"].items():
            assert 0 < cpu <= (os.cpu_count() + 0.5) * r["process_s"][label], (label, cpu)
        assert all(v > 50 for v in r["peak_mib"].values())  # a Python process with NumPy
        assert 0 < r["frame_ms"]["median"] <= r["frame_ms"]["p95"]
    assert ours["queries_per_frame"] >= 1 and ours["frames"] == 4
    # Where each ran: timings (and our methods' last digits) depend on the CPU and versions.
    from importlib.metadata import version

    for r in (ours, peer):
        assert r["machine"]["cores"] == os.cpu_count() and r["machine"]["cpu"]
        assert r["machine"]["jax"] == version("jax") and r["commit"]
    assert peer["machine"]["small_gicp"] == version("small_gicp")
    assert "small_gicp" not in ours["machine"]
    rows = [line for line in printed.splitlines() if line.startswith("| 00 |")]
    cells = rows[0].strip("| ").split(" | ")
    ratio = ours["frame_ms"]["median"] / peer["frame_ms"]["median"]
    assert cells[1] == "gicp" and cells[5] == f"{ratio:.2f}x"
    assert cells[7].count(" / ") == 1 and cells[9].count(" / ") == 1
    assert cells[8] == f"{ours['cpu_s']['cached'] / ours['process_s']['cached']:.2f}"


def test_rounds_take_each_ratio_within_its_own_round(bench_odometry):
    """--rounds: round r > 1 is keyed name/method@r, and every ratio (the speed table's
    against small_gicp, the ratio table's against gicp and small_gicp) compares runs of the
    same round, whatever the machine did between rounds."""

    def run(ms: float) -> dict:
        frame = {"median": ms, "p95": 1.5 * ms}
        return {"t_err_percent": 0.2, "r_err_deg_per_100m": 0.1, "frame_ms": frame,
                "median_ms_per_frame": ms}  # fmt: skip

    # round 2 ran on a machine 50 % slower
    results = {"9/gicp": run(60.0), "9/gloam": run(75.0), "9/small_gicp": run(40.0)}
    results |= {"9/gicp@2": run(90.0), "9/gloam@2": run(114.0), "9/small_gicp@2": run(60.0)}
    ratios = bench_odometry.ratio_table(results)
    assert "| 9 | gloam | gicp | 1.25, 1.27 | 1.26x |" in ratios
    assert "| 9 | gicp | small_gicp | 1.50, 1.50 | 1.50x |" in ratios
    speed = bench_odometry.speed_table(results)
    assert "| 9 | gicp@2 | 0.200 | 0.100 | 90.0 / 135.0 | 1.50x |" in speed


def test_a_method_that_cannot_run_is_named_before_any_run(bench_odometry, tmp_path, monkeypatch):
    """A half-hour sitting stops at the start, not at its last method: a peer whose package is
    missing, or a method of ours without a config in --configs."""
    from repo_scripts import ROOT

    configs = ROOT / "configs"
    assert bench_odometry.unrunnable(["gicp", "gloam", "small_gicp"], configs) is None
    kiss = bench_odometry.PEERS["kiss-icp"]
    monkeypatch.setitem(bench_odometry.PEERS, "kiss-icp", kiss._replace(module="no_such_package"))
    problem = bench_odometry.unrunnable(["gicp", "kiss-icp"], configs)
    assert problem == "kiss-icp: its package is not installed (pip install -e '.[peers]')"
    problem = bench_odometry.unrunnable(["gicp"], tmp_path)  # an empty --configs folder
    missing = tmp_path / "gicp.yaml"
    assert problem == f"gicp: neither a peer nor a config of ours ({missing} is missing)"
