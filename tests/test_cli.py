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


def test_eval_falls_back_to_ate_on_a_short_path(tmp_path):
    gt = straight_line(30)  # 29 m: shorter than the devkit's 100 m segments
    est = gt.copy()
    est[:, 0, 3] += 0.1 * np.sin(np.arange(30))
    io.write_kitti_poses(tmp_path / "gt.txt", gt)
    io.write_kitti_poses(tmp_path / "est.txt", est)
    args = ["--json", str(tmp_path / "m.json"), "--plot", str(tmp_path / "p.png")]
    result = runner.invoke(
        app, ["eval", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), *args]
    )
    assert result.exit_code == 0, result.output
    assert "RTE unavailable" in result.output and "ATE" in result.output
    said = " ".join(result.output.split())  # rich wraps at the terminal's width
    assert "drift +0.00 +0.00 +0.00 mdeg" in said  # the error moves, never turns
    metrics = json.loads((tmp_path / "m.json").read_text())
    assert "no segment fits" in metrics["rte_unavailable"]
    assert 0.03 < metrics["ate"]["rmse"] < 0.1  # the 0.1 m sine, less what alignment absorbs
    drift = metrics["frame_rotation"]  # the sine moves, never turns: no rotation error
    assert drift["num_frames"] == 29 and np.abs(drift["mean_mdeg"]).max() < 1e-6
    assert (tmp_path / "p.png").stat().st_size > 10_000


def test_run_method_by_name_and_weights_it_cannot_take(tmp_path):
    from gloam_jax.cli.run import method_settings
    from gloam_jax.config import load_config
    from gloam_jax.errors import InputError

    assert method_settings(None, "gicp_ce", None) == load_config("gicp_ce")
    assert method_settings(None, "gloam", tmp_path / "m.npz").model == str(tmp_path / "m.npz")
    for args, message in [
        (["--method", "gicp", "--weights", "model.npz"], "method 'gicp' learns nothing"),
        (["--config", "gicp", "--weights", "model.npz"], "method 'gicp' learns nothing"),
        (["--method", "gicp", "--config", "gloam"], "give --method or --config, not both"),
        (["--method", "icp"], "unknown --method 'icp'"),
    ]:
        result = runner.invoke(app, ["run", str(tmp_path), *args, "--out", str(tmp_path / "r")])
        assert result.exit_code == 2 and message in result.output, result.output
        assert len(result.output.strip().splitlines()) == 1
    with pytest.raises(InputError, match="learns nothing"):
        method_settings(None, "gicp", tmp_path / "m.npz")


@pytest.mark.parametrize("name", ["gloam", "gicp", "train_grad"])
def test_config_dump_writes_commented_yaml_that_loads_back(tmp_path, name):
    from gloam_jax.config import load_config
    from gloam_jax.training.config import TrainConfig

    cls = TrainConfig if name.startswith("train") else None
    out = tmp_path / f"{name}.yaml"
    result = runner.invoke(app, ["config", "dump", name, "--out", str(out)])
    assert result.exit_code == 0, result.output
    text = out.read_text()
    assert "# m; closer returns" in text and "min_range: 3.0" in text
    if cls is None:
        assert load_config(out) == load_config(name)
        assert "deskew: auto" in text
    else:
        assert load_config(out, cls) == load_config(name, cls)
    printed = runner.invoke(app, ["config", "dump", name])
    assert printed.exit_code == 0 and printed.output == text
    missing = runner.invoke(app, ["config", "dump", "glom"])
    assert missing.exit_code == 2 and "nor a shipped config" in missing.output


def test_config_docs_are_current():
    import runpy
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    script = runpy.run_path(str(root / "scripts" / "config_docs.py"))
    page = (root / "docs" / "config.md").read_text()
    assert page == script["render"](), "stale: python scripts/config_docs.py --write docs/config.md"
    for name in ("preprocess.deskew", "gicp.max_correspondence_distance", "batch.gicp.adjoint",
                 "tpe.n_trials", "grad.learning_rate", "keyframe_distance"):  # fmt: skip
        assert f"| `{name}` |" in page


def test_plain_progress_lines_when_not_a_terminal(capsys):
    from gloam_jax.cli.common import console, frame_progress

    assert not console.is_terminal  # pytest captures stdout
    with frame_progress("gicp 00", 25, every=10) as step:
        for k in range(25):
            step(k, 12.0)
    lines = capsys.readouterr().out.strip().splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "gicp 00: frame 10/25 (40 %)",
        "gicp 00: frame 20/25 (80 %)",
        "gicp 00: frame 25/25 (100 %)",
    ]
    assert all("frames/s" in line and "ETA" in line for line in lines)


def test_compilation_cache_lives_in_the_user_cache_and_can_be_turned_off(tmp_path, monkeypatch):
    import jax

    from gloam_jax.cli.common import use_compilation_cache

    before = (
        jax.config.jax_compilation_cache_dir,
        jax.config.jax_persistent_cache_min_compile_time_secs,
    )
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    try:
        monkeypatch.setenv("GLOAM_COMPILATION_CACHE", "0")
        assert use_compilation_cache() is None and jax.config.jax_compilation_cache_dir == before[0]
        monkeypatch.delenv("GLOAM_COMPILATION_CACHE")
        folder = use_compilation_cache()
        assert folder == tmp_path / "gloam-jax" / "jax" and folder.is_dir()
        assert jax.config.jax_compilation_cache_dir == str(folder)
    finally:
        jax.config.update("jax_compilation_cache_dir", before[0])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", before[1])


def _config_class(path):
    from gloam_jax.odometry import OdometryConfig
    from gloam_jax.training.config import TrainConfig

    return TrainConfig if path.stem.startswith("train") else OdometryConfig


def test_every_shipped_config_loads():
    """Each YAML under gloam_jax/configs/ builds its dataclass, its base chain included: the
    method configs and the few training configs a user starts from."""
    from pathlib import Path

    import gloam_jax
    from gloam_jax.config import load_config

    paths = sorted((Path(gloam_jax.__file__).parent / "configs").glob("*.yaml"))
    assert {"gicp", "gicp_da", "gicp_ce", "gloam", "train_grad", "train_tpe", "train_protocol"} <= {
        p.stem for p in paths
    }
    assert len(paths) <= 10
    for path in paths:
        load_config(path.stem, _config_class(path))


def test_every_experiment_config_loads_from_its_folder():
    """The experiments' configs load with --config PATH, their bases read relative to them."""
    from pathlib import Path

    from gloam_jax.config import load_config

    paths = sorted((Path(__file__).resolve().parents[1] / "experiments").rglob("*.yaml"))
    assert len(paths) >= 15
    for path in paths:
        config = load_config(str(path), _config_class(path))
        if path.stem.endswith("_warmup"):
            assert config.grad.warmup_steps == 20 and config.grad.steps == 60


def test_the_shipped_protocol_configs_are_the_experiments_that_made_the_shipped_models():
    """configs/train_protocol.yaml, train_net.yaml and train_hdl64.yaml are written out in one
    file each; they resolve to the same settings as the experiment chains that trained the
    shipped models, and to the settings recorded in those model files. The net model's network
    (gloam_net_backbone.npz) records its own chain's settings."""
    from pathlib import Path

    from gloam_jax.config import load_config
    from gloam_jax.features.net import load_net
    from gloam_jax.models import load_model, shipped_model_path
    from gloam_jax.training.config import TrainConfig

    experiments = Path(__file__).resolve().parents[1] / "experiments"
    network = shipped_model_path("net").with_name("gloam_net_backbone.npz")
    chain = str(experiments / "net_protocol/train_protocol_net_rank_finetune.yaml")
    made = [(load_config(chain, TrainConfig), load_net(network)[1]["config"])]
    for shipped, chain, model in (
        ("train_protocol", "w11_warmup/train_protocol_11_warmup.yaml", "default"),
        ("train_net", "net_long/train_net_long.yaml", "net"),
        ("train_hdl64", "grid_features/train_grid.yaml", "hdl64"),
    ):
        config = load_config(shipped, TrainConfig)
        assert config == load_config(str(experiments / chain), TrainConfig)
        made.append((config, load_model(model).provenance["config"]))
    for config, recorded in made:
        assert recorded["sequences"] == list(config.sequences)
        assert recorded["validation"] == list(config.validation)
        # (the net's network predates the warm-up setting, whose default 0 is no warm-up)
        assert (recorded["grad"].get("warmup_steps") or 0) == config.grad.warmup_steps
        assert recorded["grad"]["head_learning_rate"] == config.grad.head_learning_rate
        assert (recorded["backbone"], recorded["backbone_weights"]) == (
            config.backbone,
            config.backbone_weights,
        )
        # (files from before the setting recorded none, which is its default)
        assert recorded.get("backbone_options", {}) == config.backbone_options


def test_model_info_says_how_a_model_was_made(tmp_path):
    import dataclasses

    import jax

    from gloam_jax.features import fit_pca
    from gloam_jax.models import init_model, save_model

    pca = fit_pca(np.random.default_rng(0).normal(size=(100, 8)))
    bare = init_model(jax.random.PRNGKey(0), pca)
    score = {
        "method": "gloam",
        "worlds": ["301", "302", "303"],
        "sim_seeds": [0, 1],
        "commit": "abc1234 (+ uncommitted changes)",
        "date": "2026-12-05T00:00:00+00:00",
        "t_err": {"mean": 0.2822, "std": 0.0231},
        "r_err": {"mean": 0.987, "std": 0.079},
    }
    # A second look at three worlds of one simulation seed: no spread.
    rescore = {**score, "worlds": ["302", "305", "307"], "sim_seeds": [2]}
    rescore |= {"t_err": {"mean": 0.174, "std": None}, "r_err": {"mean": 0.71, "std": None}}
    provenance = {
        "mode": "grad",
        "method": "gloam",
        "seed": 2,
        "steps": 60,
        "config": {"data": "data/w", "sequences": ["101", "102"]},
        "objective": "gicp_ratio",
        "selected_on": "validation",
        "selected_value": 0.8198,
        "validation_gicp": 1.0035,
        "test_scores": [score, rescore],
    }
    save_model(tmp_path / "m.npz", dataclasses.replace(bare, provenance=provenance))
    save_model(tmp_path / "bare.npz", bare)

    shown = runner.invoke(app, ["model-info", str(tmp_path / "m.npz")], env={"COLUMNS": "120"})
    assert shown.exit_code == 0, shown.output
    for text in (
        "seed 2, 60 steps",
        "sequences 101, 102",
        "chosen on validation: gicp_ratio 0.8198",
        "(plain GICP 1.0035)",
        "worlds 301-303 (3)",
        "0.282 ± 0.023",
        "(abc1234, 2026-12-05)",
        "worlds 302, 305, 307 (3), simulation seeds 2: t_err 0.174 ± n/a %",
    ):
        assert text in shown.output, text
    as_json = runner.invoke(app, ["model-info", str(tmp_path / "m.npz"), "--json"])
    assert json.loads(as_json.output)["provenance"] == provenance
    untrained = runner.invoke(app, ["model-info", str(tmp_path / "bare.npz")])
    assert untrained.exit_code == 0 and "untrained (not written by gloam train)" in untrained.output
    # The shipped model was chosen on validation and scored on test.
    shipped = runner.invoke(app, ["model-info"], env={"COLUMNS": "120"})
    assert "chosen on validation" in shipped.output and "301-310 (10)" in shipped.output
    assert "trained for sensor hdl64: 64 rings" in shipped.output
    assert "sensors: not recorded" in untrained.output  # a file written without the record
    missing = runner.invoke(app, ["model-info", str(tmp_path / "none.npz")])
    assert missing.exit_code == 2 and "none.npz: model file not found" in missing.output
