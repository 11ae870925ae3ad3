"""The `gloam` command line, run in-process."""

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from gloam_jax import __version__, io
from gloam_jax.cli import app

runner = CliRunner()


def straight_line(n: int, step: float = 1.0) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 2, 3] = step * np.arange(n)  # camera-0 convention: forward is z
    return T


def test_version():
    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0
    assert __version__ in result.output


def test_eval_writes_devkit_metrics(tmp_path):
    gt = straight_line(301)
    est = gt.copy()
    est[:, 2, 3] *= 1.01  # 1 % scale drift
    io.write_kitti_poses(tmp_path / "gt.txt", gt)
    io.write_kitti_poses(tmp_path / "est.txt", est)
    out = tmp_path / "m.json"
    result = runner.invoke(
        app,
        ["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "--json", str(out),
         "--plot", str(tmp_path / "p.png")],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    metrics = json.loads(out.read_text())
    assert {"t_err_percent", "r_err_deg_per_100m", "num_segments", "per_length"} <= set(metrics)
    # Segments span one frame more than their nominal length, as in the devkit.
    expected = {100: 1.0 * 101 / 100, 200: 1.0 * 201 / 200}
    for length, value in expected.items():
        assert abs(metrics["per_length"][str(length)]["t_err_percent"] - value) < 1e-4
    assert metrics["r_err_deg_per_100m"] < 1e-6
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_eval_mismatched_lengths_is_one_clear_line(tmp_path):
    io.write_kitti_poses(tmp_path / "gt.txt", straight_line(300))
    io.write_kitti_poses(tmp_path / "est.txt", straight_line(299))
    result = runner.invoke(app, ["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt")])
    assert result.exit_code == 2
    assert "est.txt: 299 poses vs 300" in result.output
    assert "Traceback" not in result.output


def test_eval_missing_file(tmp_path):
    io.write_kitti_poses(tmp_path / "gt.txt", straight_line(300))
    result = runner.invoke(app, ["eval", str(tmp_path / "gt.txt"), str(tmp_path / "nope.txt")])
    assert result.exit_code == 2
    assert "nope.txt" in result.output and "Traceback" not in result.output


def test_simulate_small_sequence(tmp_path):
    result = runner.invoke(
        app,
        ["simulate", str(tmp_path), "--frames", "2", "--beams", "16", "--columns", "400",
         "--style", "highway", "--sequence", "07"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    seq = io.KittiSequence(tmp_path, "07")
    assert len(seq) == 2 and len(seq.scan(0)) > 1000
    bad = runner.invoke(app, ["simulate", str(tmp_path / "x"), "--style", "desert"])
    assert bad.exit_code == 2 and "unknown scene style 'desert'" in bad.output


def test_run_folders_are_exclusive_and_latest_is_replaced_atomically(tmp_path):
    from gloam_jax.cli.common import run_folder

    with run_folder(tmp_path) as first, run_folder(tmp_path) as second:
        assert first != second and first.is_dir() and second.is_dir()
    assert (tmp_path / "latest").resolve() == first.resolve()  # the run that finished last
    assert not list(tmp_path.glob(".latest-*"))  # no temporary link left
    with pytest.raises(RuntimeError), run_folder(tmp_path) as failed:
        raise RuntimeError("the run failed")
    assert not failed.exists() and (tmp_path / "latest").resolve() == first.resolve()


def test_run_folder_refuses_a_real_latest_directory_and_an_unwritable_root(tmp_path):
    from gloam_jax.cli.common import run_folder
    from gloam_jax.errors import InputError

    (tmp_path / "latest").mkdir()
    with pytest.raises(InputError, match="latest: is not a link to a run"), run_folder(tmp_path):
        pass
    (tmp_path / "file").write_text("not a folder")
    with (
        pytest.raises(InputError, match="cannot create a run folder"),
        run_folder(tmp_path / "file" / "results"),
    ):
        pass
