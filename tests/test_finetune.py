"""Fine-tuning the net backbone's last layer through the odometry loss (gradient mode): the
features it recomputes are the inference path's, training moves the layer, the export loads."""

import shutil

import jax
import numpy as np
import pytest

from gloam_jax.errors import InputError
from gloam_jax.features import get_backbone
from gloam_jax.features.net import NetConfig, SegNet, load_net, save_net
from gloam_jax.models import load_model, save_model
from gloam_jax.training.config import GradConfig
from gloam_jax.training.data import load_windows
from gloam_jax.training.grad import train_grad
from gloam_jax.training.head import head_features
from gloam_jax.training.problem import fit_initial_model, setup

# One worker runs this module (pytest-xdist --dist loadgroup): its start model is made once.
pytestmark = pytest.mark.xdist_group("finetune")

GRAD = GradConfig(steps=2, eval_every=1, learning_rate=0.01, head_learning_rate=0.01)


@pytest.fixture(scope="module")
def net_start(sim_sequence, tmp_path_factory):
    """An untrained small network and a GICP start model on its features (PCA on 4 scans)."""
    folder = tmp_path_factory.mktemp("finetune")
    toy = SegNet(NetConfig(k=8), key=jax.random.key(3))
    save_net(folder / "net.npz", toy, {"note": "toy", "intensity_mean": 0.5})
    backbone = get_backbone("net", weights=str(folder / "net.npz"))
    model = fit_initial_model(sim_sequence, ["00"], backbone, every=10, init="gicp")
    save_model(folder / "start.npz", model)
    return folder / "start.npz"


def _features_by_inference(sim_sequence, problem, model):
    """The scans' PCA features as inference makes them: the model's backbone on raw scans,
    then the preprocessing's voxel means (the batch's own preparation)."""
    cfg = problem.config
    data = load_windows(sim_sequence, ["00"], cfg.preprocess, cfg.batch, model.pca,
                        model.backbone(), frames=cfg.frames)  # fmt: skip
    return np.asarray(data.scans.pca), np.asarray(data.scans.mask)


def test_recomputed_features_are_the_backbones_and_training_exports_the_layer(
    sim_sequence, tiny_training, net_start, tmp_path
):
    cfg = tiny_training.config(mode="grad", init_model=str(net_start), grad=GRAD)
    problem = setup(cfg, tmp_path / "run")
    start = problem.init_params
    assert start.head is not None
    shape = problem.data.scans.mask.shape
    mask = np.asarray(problem.data.scans.mask)
    # The start layer gives exactly the prepared features (inference's path), padding zero.
    got = np.asarray(head_features(start.head, problem.data.head, shape))
    want = np.asarray(problem.data.scans.pca)
    scale = np.abs(want[mask]).max()
    np.testing.assert_allclose(got[mask], want[mask], atol=1e-5 * scale)
    assert not got[~mask].any()

    trained = train_grad(problem)
    run = tmp_path / "run"
    net, provenance = load_net(run / "net.npz")
    before, _ = load_net(net_start.parent / "net.npz")
    assert provenance["layers"] == "decode" and provenance["steps"] == 2
    assert provenance["intensity_mean"] == 0.5  # the inputs, so the run check, are the same
    assert not np.allclose(net.decode.weight, before.decode.weight)  # the layer moved
    np.testing.assert_array_equal(net.local1.out.weight, before.local1.out.weight)  # the rest not
    # The exported model names its network beside it; inference on its backbone gives the
    # features that training computed for the trained layer.
    model = load_model(run / "model.npz")
    assert model.backbone_options["weights"] == str(run / "net.npz")
    # Rewritten in place (as make_tables appends a test score), the file still names the
    # network beside it, so a copy of the folder loads anywhere.
    save_model(run / "model.npz", model)
    moved = shutil.copytree(run, tmp_path / "moved")
    assert load_model(moved / "model.npz").backbone_options["weights"] == str(moved / "net.npz")
    assert trained.backbone().net.decode.weight.shape == net.decode.weight.shape
    head = problem.init_params.head._replace(weight=net.decode.weight, bias=net.decode.bias)
    tuned = np.asarray(head_features(head, problem.data.head, shape))
    by_inference, _ = _features_by_inference(sim_sequence, problem, model)
    np.testing.assert_allclose(tuned[mask], by_inference[mask], atol=1e-5 * scale)
    assert not np.allclose(tuned[mask], want[mask], atol=1e-5 * scale)


def test_fine_tuning_needs_the_net_backbone_in_gradient_mode(tiny_training, tmp_path):
    cfg = tiny_training.config(mode="grad", grad=GRAD)  # the geometric start
    with pytest.raises(InputError, match="fine-tunes the net backbone in gradient mode"):
        setup(cfg, tmp_path / "run")
    with pytest.raises(InputError, match="head_learning_rate must be positive"):
        GradConfig(head_learning_rate=0.0)


def test_a_run_without_a_start_model_fits_the_pca_on_the_configured_backbone(
    tiny_training, tmp_path
):
    cfg = tiny_training.config(init_model=None, backbone="net", pca_every=3, grad=GRAD)
    problem = setup(cfg, tmp_path / "run")
    start = load_model(tmp_path / "run" / "init_model.npz")
    assert start.backbone_name == "net" and start.pca.components.shape == (6, 32)
    assert problem.init_params.head is not None  # the net start can be fine-tuned
