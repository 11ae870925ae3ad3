"""scripts/eval_batch.py: which weights a model argument loads, and what it refuses; its
--plane-eps rows; probe_thickness.py, which loads models through it."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from repo_scripts import import_script

from gloam_jax.config import dump_config, load_config
from gloam_jax.models import load_model, shipped_model_path
from gloam_jax.training.config import TrainConfig

eval_batch = import_script("eval_batch")


def test_a_model_file_loads_as_itself():
    loaded = eval_batch._load(shipped_model_path())
    # Bit for bit: the same file read twice, nothing computed.
    np.testing.assert_array_equal(
        loaded.pca.components, load_model(shipped_model_path()).pca.components
    )


def test_a_fine_tuning_runs_checkpoint_is_refused_in_one_line(tmp_path):
    # Its MLPs fit the fine-tuned layer's features; scored on the frozen ones they would mislead.
    finetune = Path(__file__).resolve().parents[1] / "experiments/net_protocol"
    config = load_config(str(finetune / "train_protocol_net_rank_finetune.yaml"), TrainConfig)
    dump_config(config, tmp_path / "config.yaml")
    (tmp_path / "checkpoint.npz").write_bytes(b"")
    with pytest.raises(SystemExit) as refused:
        eval_batch._load(tmp_path / "checkpoint.npz")
    message = str(refused.value)
    assert "\n" not in message and "fine-tuning run's checkpoint" in message
    assert "model.npz" in message and str(tmp_path / "checkpoint.npz") in message


def test_plane_eps_rows_are_gicp_with_thicker_planes(tiny_training, tmp_path, monkeypatch):
    """GICP's own eps as a constant eigenvalue MLP gives GICP's errors; a thicker plane
    changes them. A thickness bound above the start's planes changes nothing."""
    import json
    import sys

    config = tmp_path / "config.yaml"
    dump_config(tiny_training.config(), config)
    out = tmp_path / "eval.json"
    monkeypatch.setattr(sys, "argv", [
        "eval_batch.py", "--config", str(config), "--sequences", "00",
        "--model", f"start={tiny_training.start}", "--plane-eps", "0.001,0.03",
        "--max-thickness", "0.01", "--cache", str(tmp_path / "cache"), "--out", str(out),
    ])  # fmt: skip
    eval_batch.main()
    rows = json.loads(out.read_text())
    gicp = rows["GICP"]["mean"]
    assert rows["GICP, plane eps 0.001"]["mean"] == pytest.approx(gicp, rel=1e-4)
    assert abs(rows["GICP, plane eps 0.03"]["mean"] - gicp) > 1e-3 * gicp
    # The start's planes are GICP's, far thinner than the bound: the bounded row is the start's.
    # The bound is another compiled program (its cap in it): float32 noise through the solves
    # (~5e-6 relative, issue 45), 1e-4 as for the plane eps row above.
    assert rows["start, planes <= 0.01"]["mean"] == pytest.approx(rows["start"]["mean"], rel=1e-4)


def test_thickness_probe_and_the_thickness_cap(tiny_training):
    """probe_thickness.py: the GICP start's planes are eps thick on every centre; weights that
    output (0.05, 1, 1) everywhere are 0.05 thick, 0.01 under a max_thickness of 0.01."""
    from gloam_jax.datasets import open_dataset
    from gloam_jax.learned import plane_output
    from gloam_jax.preprocess import PreprocessConfig

    probe = import_script("probe_thickness", experiment="plane_thickness")
    model = tiny_training.model
    scan = open_dataset(tiny_training.config().data, "00").frame(0)[0]
    config = PreprocessConfig()

    def thickness(m):
        values = probe.learned_values(m, scan, config)
        return values[:, 0] / values[:, 1]

    start = thickness(model)
    assert len(start) > 100
    np.testing.assert_allclose(start, model.eps, rtol=1e-5)
    disc = probe.learned_values(model, scan, config)  # GICP's plane is round within itself
    np.testing.assert_allclose(disc[:, 1] / disc[:, 2], 1.0, rtol=1e-5)
    thick = dataclasses.replace(model, eigenvalue=model.eigenvalue.constant(plane_output(0.05)))
    np.testing.assert_allclose(thickness(thick), 0.05, rtol=1e-5)
    # A model's max_thickness (eval_batch --max-thickness): planes thinned to the bound,
    # thinner ones left as they are; the probe measures what the model registers with.
    capped = dataclasses.replace(thick, max_thickness=0.01)
    np.testing.assert_allclose(thickness(capped), 0.01, rtol=1e-5)
    kept = dataclasses.replace(model, max_thickness=0.01)
    np.testing.assert_allclose(thickness(kept), model.eps, rtol=1e-5)


def test_thickness_probe_pools_the_listed_worlds(tiny_training, tmp_path):
    """probe_thickness.py's "all" column: the statistics of every listed world's points
    together (here one world listed twice: the same as the world's own)."""
    probe = import_script("probe_thickness", experiment="plane_thickness")
    out = tmp_path / "thick.json"
    root = tiny_training.config().data
    argv = ["--data", root, "--sequences", "00,00", "--every", "5", "--out", str(out)]
    probe.main([*argv, "--model", f"start={tiny_training.start}"])
    row = json.loads(out.read_text())["start"]
    assert row["all"] == row["00"]
    assert row["all"]["median"] == pytest.approx(tiny_training.model.eps, rel=1e-5)
    assert row["all"]["thick_share"] == 0.0
