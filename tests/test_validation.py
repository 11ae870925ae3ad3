"""Settings and model files check themselves: a bad value is one clear error where it is made,
never a silent change of meaning or a traceback later."""

import dataclasses

import jax
import numpy as np
import pytest

from gloam_jax.config import load_config
from gloam_jax.errors import InputError
from gloam_jax.gicp import GICPConfig
from gloam_jax.odometry import OdometryConfig


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("num_candidates", 0, "gicp.num_candidates must be an integer >= 1"),
        ("num_candidates", 2.5, "gicp.num_candidates must be an integer >= 1"),
        ("max_iterations", True, "gicp.max_iterations must be an integer >= 1"),
        ("inner_steps", 1, "gicp.inner_steps must be an integer >= 2"),
        ("max_correspondence_distance", -0.5, "max_correspondence_distance must be positive"),
        ("rotation_eps", float("nan"), "gicp.rotation_eps must be positive"),
        ("degeneracy_threshold", -1e-4, "gicp.degeneracy_threshold must be positive"),
        ("lever_arm", 0.0, "gicp.lever_arm must be positive"),
    ],
)
def test_gicp_settings(field, value, message):
    with pytest.raises(InputError, match=message):
        GICPConfig(**{field: value})


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("max_keyframes", 0, "max_keyframes must be an integer >= 1"),
        ("keyframe_distance", 0.0, "keyframe_distance must be positive"),
        ("map_resolution", -0.5, r"map_resolution must be 0, positive \(m\) or auto"),
        ("map_resolution", "fine", "map_resolution must be 0, positive .* not 'fine'"),
        ("map_resolution", False, "map_resolution must be 0, positive .* not False"),
    ],
)
def test_odometry_settings(field, value, message):
    with pytest.raises(InputError, match=message):
        OdometryConfig(**{field: value})


def test_yaml_errors_name_the_file_and_the_setting(tmp_path):
    cases = {
        "gicp:\n  num_candidates: 2.5\n": "gicp.num_candidates must be a whole number, not 2.5",
        "gicp:\n  num_candidates: 0\n": "gicp.num_candidates must be an integer >= 1, not 0",
        "max_keyframes: 0\n": "max_keyframes must be an integer >= 1",
    }
    for text, message in cases.items():
        path = tmp_path / "c.yaml"
        path.write_text(text)
        with pytest.raises(InputError, match=f"c.yaml: {message}"):
            load_config(path)
    (tmp_path / "binary.yaml").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(InputError, match="binary.yaml: not a text file"):
        load_config(tmp_path / "binary.yaml")
    with pytest.raises(InputError, match="is a directory"):
        load_config(tmp_path)


def _model(width: int = 12):
    from gloam_jax.features import fit_pca
    from gloam_jax.models import init_model

    pca = fit_pca(np.random.default_rng(0).normal(size=(50, width)))
    return init_model(jax.random.PRNGKey(0), pca)


def test_a_model_whose_backbone_gives_another_width_is_refused():
    assert _model(20).backbone().dim == 20  # the geometric backbone's width
    with pytest.raises(InputError, match="PCA expects 12 features per point, but its backbone"):
        _model(12).backbone()


def test_a_model_with_a_zero_pca_scale_is_refused(tmp_path):
    from gloam_jax.models import load_model, save_model

    model = _model()
    scale = model.pca.scale.copy()
    scale[3] = 0.0
    save_model(tmp_path / "m.npz", dataclasses.replace(model, pca=model.pca._replace(scale=scale)))
    with pytest.raises(InputError, match="m.npz: 'pca_scale' must be positive"):
        load_model(tmp_path / "m.npz")


def test_eval_refuses_rotation_blocks_that_are_not_rotations(tmp_path):
    from gloam_jax import io, metrics

    gt = np.tile(np.eye(4), (5, 1, 1))
    gt[:, 0, 3] = np.arange(5.0)
    for bad, how in ((3.0, "scaled"), (0.0, "zeroed")):
        est = gt.copy()
        est[2, :3, :3] *= bad
        with pytest.raises(InputError, match=f"{how}.txt: estimated pose 2 has a rotation block"):
            metrics.ate(gt, est, source=f"{how}.txt")
        np.savetxt(tmp_path / f"{how}.txt", est[:, :3].reshape(5, 12))
        with pytest.raises(InputError, match="pose 2 has a rotation block that is not a rotation"):
            metrics.evaluate(gt, io.read_kitti_poses(tmp_path / f"{how}.txt"))


def test_a_singular_calibration_is_refused(tmp_path):
    from gloam_jax import io

    (tmp_path / "calib.txt").write_text("Tr: 0 0 0 0 0 0 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match=r"calib.txt: line 1 \(Tr\) is not a rigid transform"):
        io.read_calib(tmp_path / "calib.txt")
