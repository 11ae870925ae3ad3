"""The ``net`` backbone: its network, training step, weight files and use inside ``gloam run``."""

import json
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
import pytest
from scipy.spatial import cKDTree
from typer.testing import CliRunner

from gloam_jax import pointcloud as pc
from gloam_jax.cli import app
from gloam_jax.errors import InputError
from gloam_jax.features import fit_pca, get_backbone, intensity_warning
from gloam_jax.features import net as net_module
from gloam_jax.features.net import (
    CLASSES,
    LocalAggregation,
    NetConfig,
    SegNet,
    class_index,
    load_net,
    run_scan,
    save_net,
)
from gloam_jax.models import init_model, save_model, shipped_model_path
from gloam_jax.preprocess import PreprocessConfig, voxel_centres
from gloam_jax.training.segmentation import (
    LabelledScan,
    SegmentationConfig,
    class_weights,
    draw_batch,
    make_optimizer,
    make_step,
)

SMALL = NetConfig(k=8)


def toy_scan(seed: int = 0, n: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Road plane, a wall and a pole: points (n, 4) and SemanticKITTI labels (n,)."""
    rng = np.random.default_rng(seed)
    a, b, c = n // 2, n // 3, n - n // 2 - n // 3
    road = np.c_[rng.uniform(-8, 8, (a, 2)), rng.normal(-1.7, 0.01, a)]
    wall = np.c_[rng.uniform(-8, 8, b), np.full(b, 5.0), rng.uniform(-1.7, 4, b)]
    pole = np.c_[rng.normal(3, 0.05, (c, 2)), rng.uniform(-1.7, 3, c)]
    xyz = np.concatenate([road, wall, pole])
    labels = np.repeat(np.array([40, 50, 80], np.uint16), [a, b, c])
    return np.c_[xyz, rng.uniform(0, 1, n)].astype(np.float32), labels


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    path = tmp_path_factory.mktemp("net") / "net.npz"
    save_net(path, SegNet(SMALL, key=jax.random.key(1)), {"note": "untrained"})
    return path


def test_class_index_folds_moving_objects_and_drops_unknown_ids():
    ids = class_index(np.array([0, 10, 252, 40, 81, 99, 1 << 16 | 50, 254], np.uint32))
    assert [CLASSES[i] if i >= 0 else None for i in ids] == [
        None, "car", "car", "road", "traffic-sign", None, "building", "person",
    ]  # fmt: skip


def test_backbone_shapes_rows_and_permutation_invariance(weights):
    backbone = get_backbone("net", weights=str(weights))
    assert get_backbone(backbone.name, **backbone.options()).weights == str(weights)
    scan, _ = toy_scan()
    scan[5] = np.nan  # a bad row keeps its place, with zero features
    f = backbone(scan)
    assert f.shape == (len(scan), backbone.dim) == (len(scan), 32) and f.dtype == np.float32
    assert np.all(f[5] == 0) and np.all(np.isfinite(f)) and f.std(axis=0).max() > 0
    perm = np.random.default_rng(3).permutation(len(scan))
    np.testing.assert_allclose(backbone(scan[perm]), f[perm], atol=1e-4, rtol=1e-4)
    # Three columns (no intensity) and a cloud smaller than k work too.
    assert backbone(scan[:5, :3]).shape == (5, 32)
    with pytest.raises(InputError, match="expected an"):
        backbone(scan[:, :2])


def _attentive_pooling(layer, h, xyz, nbr):
    """RandLA-Net's local aggregation as written in one piece: the reference."""
    rel = xyz[nbr] - xyz[:, None, :]
    enc = jax.nn.relu(
        layer.position(np.concatenate([rel, np.linalg.norm(rel, axis=-1)[..., None]], -1))
    )
    fh = np.concatenate([enc, jax.nn.relu(layer.feature(h))[nbr]], axis=-1)
    attention = jax.nn.softmax(layer.score(fh), axis=1)
    return jax.nn.relu(layer.out(np.sum(attention * fh, axis=1)))


@pytest.mark.parametrize("k", [2, 10])
def test_each_voxel_upsamples_from_its_nearest_level1_point(k):
    """The nearest sampled voxel read off the level-0 k-NN rows is the level-1 tree's nearest
    (k = 2: most rows have no sampled neighbour and query the tree; k = 10: a few)."""
    from gloam_jax.neighbors import KdTree

    xyz = np.random.default_rng(4).uniform(-20, 20, (5000, 3))
    sub = net_module.sample_level1(len(xyz), 4)
    tree1 = KdTree(xyz[sub])
    nbr0 = net_module._knn(KdTree(xyz), xyz, k)
    want = cKDTree(xyz[sub]).query(xyz, 1)[1]
    up = net_module.nearest_sampled(nbr0, sub, tree1, xyz)
    assert up.dtype == np.int32
    np.testing.assert_array_equal(up, want)
    np.testing.assert_array_equal(up[sub], np.arange(len(sub)))  # sampled voxels: themselves


@pytest.mark.parametrize(
    ("backend", "chunk_bytes"), [("cpu", 1 << 21), ("cpu", 3000), ("gpu", 3000)]
)
def test_local_aggregation_in_chunks_is_the_one_piece_formula(monkeypatch, backend, chunk_bytes):
    # 3000 bytes: chunks of 5 rows (K = 8, 16 channels), 37 rows = 7 chunks and a remainder;
    # on an accelerator all rows at once
    monkeypatch.setattr(net_module, "_CHUNK_BYTES", chunk_bytes)
    monkeypatch.setattr(jax, "default_backend", lambda: backend)
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(37, 3)).astype(np.float32)
    h = rng.normal(size=(37, 8)).astype(np.float32)
    nbr = cKDTree(xyz).query(xyz, 8)[1].astype(np.int32)
    layer = LocalAggregation(8, 16, key=jax.random.key(3))
    want = np.asarray(_attentive_pooling(layer, h, xyz, nbr))
    got = np.asarray(eqx.filter_jit(layer.__call__)(h, xyz, nbr))
    assert got.shape == (37, 16)
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(np.asarray(layer(h, xyz, nbr)), want, atol=1e-5)  # eager, NumPy


def test_networks_blind_to_intensity_or_to_its_units(tmp_path):
    scan, _ = toy_scan()
    relit = scan.copy()
    relit[:, 3] = np.random.default_rng(5).uniform(0, 100, len(scan))  # another sensor's scale
    for intensity in (True, False):
        path = tmp_path / f"net_{intensity}.npz"
        config = NetConfig(k=8, intensity=intensity)
        save_net(path, SegNet(config, key=jax.random.key(1)), {"note": "untrained"})
        backbone = get_backbone("net", weights=str(path))
        assert backbone.net.config == config  # the flag survives the file
        same = np.allclose(backbone(scan), backbone(relit), atol=1e-6)
        assert same != intensity
    # Intensity as its rank in the scan: blind to units, gain and offset, not to another order.
    path = tmp_path / "net_rank.npz"
    save_net(path, SegNet(NetConfig(k=8, intensity_rank=True), key=jax.random.key(1)), {})
    backbone = get_backbone("net", weights=str(path))
    recalibrated = scan.copy()
    recalibrated[:, 3] = 255 * scan[:, 3] + 3  # other units and offset
    np.testing.assert_allclose(backbone(recalibrated), backbone(scan), atol=1e-6)
    assert not np.allclose(backbone(relit), backbone(scan), atol=1e-6)  # another order
    assert backbone.fitted_intensity() is None  # no units for a run to check, ...
    assert intensity_warning(backbone, None, recalibrated) is None
    flat = scan.copy()
    flat[:, 3] = 0.0
    for bare in (flat, scan[:, :3]):  # ... but an order: none without intensity
        assert "carry no intensity" in intensity_warning(backbone, None, bare)


def test_training_step_overfits_a_tiny_set():
    scan, labels = toy_scan()
    from gloam_jax.features.net import voxelize

    xyz, intensity, inverse = voxelize(scan, SMALL.voxel_size)
    votes = np.zeros((len(xyz), len(CLASSES)), int)
    np.add.at(votes, (inverse, class_index(labels)), 1)
    scans = [LabelledScan(xyz, intensity, votes.argmax(1).astype(np.int32), cKDTree(xyz))]
    cfg = SegmentationConfig(data="-", train=("00",), test=("01",), steps=60, batch=2, crop=512,
                             learning_rate=1e-2, net=SMALL)  # fmt: skip
    w = class_weights(scans)
    assert w[CLASSES.index("car")] == 0 and np.isclose(w[w > 0].mean(), 1.0)
    params, static = eqx.partition(SegNet(SMALL, key=jax.random.key(0)), eqx.is_array)
    optimizer = make_optimizer(cfg)
    state, update, losses = optimizer.init(params), make_step(optimizer), []
    for step in range(cfg.steps):
        x, y = draw_batch(scans, cfg, step)
        assert x.nbr0.shape == (2, 512, SMALL.k) and y.shape == (2, 512)
        params, state, loss = update(params, static, state, x, y, w)
        losses.append(float(loss))
    assert np.mean(losses[-10:]) < 0.3 * np.mean(losses[:5])
    _, logits = run_scan(eqx.combine(params, static), scan)
    accuracy = np.mean(logits.argmax(1) == class_index(labels))
    assert accuracy > 0.9  # road alone would be 0.5


def test_weights_round_trip_and_bad_files(tmp_path, weights):
    net, provenance = load_net(weights)
    assert provenance == {"note": "untrained"} and net.config == SMALL
    save_net(tmp_path / "again.npz", net, provenance)
    again, _ = load_net(tmp_path / "again.npz")
    scan, _ = toy_scan(1, 500)
    # Bit for bit: the same weights (the .npz is lossless) through the same program here.
    for a, b in zip(run_scan(net, scan), run_scan(again, scan), strict=True):
        np.testing.assert_array_equal(a, b)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="cannot read network weights"):
        load_net(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", metadata=np.array(json.dumps({"format": "x"})))
    with pytest.raises(InputError, match="not a gloam-jax-net file"):
        load_net(tmp_path / "other.npz")
    with pytest.raises(InputError, match="unknown backbone"):
        get_backbone("nett")


GRID = {"resolution": 0.5, "min_range": 3.0, "max_range": 100.0, "k": 10}  # the shipped configs'


def test_net_backbone_on_the_registration_grid(weights):
    backbone = get_backbone("net", weights=str(weights), grid=GRID)
    assert get_backbone("net", **backbone.options()).grid == GRID
    assert backbone.shares_grid(0.5, 3.0, 100.0) and not backbone.shares_grid(0.25, 3.0, 100.0)
    assert not get_backbone("net", weights=str(weights)).shares_grid(0.5, 3.0, 100.0)
    scan, _ = toy_scan(n=6000)
    scan[:10, :3] += np.float32([200.0, 0, 0])  # beyond max_range: zero rows
    centres = voxel_centres(scan, None, PreprocessConfig(), pca=fit_pca([backbone(scan)]),
                            backbone=backbone)  # fmt: skip
    # The covariances' neighbours are the backbone's query: the centres' exact 10-NN.
    want = cKDTree(centres.points).query(centres.points, 10)[1]
    assert centres.neighbours.shape == (len(centres.points), 10)
    assert np.mean(centres.neighbours == want) > 0.999  # ties aside
    f = backbone(scan)
    keep = pc.range_mask(scan, 3.0, 100.0)[0]  # the far ten and those within 3 m out
    assert f.shape == (len(scan), 32) and not keep[:10].any() and np.all(f[~keep] == 0)
    # every point in the band carries its 0.5 m voxel's embedding (the one voxel_centres keeps)
    grid = pc.voxel_grid(scan[keep, :3].astype(np.float64), 0.5)
    per_voxel = grid.means(f[keep].astype(np.float64))
    np.testing.assert_allclose(f[keep], per_voxel[grid.inverse], atol=1e-5)
    assert per_voxel.std(axis=0).max() > 0
    for bad in ({"resolution": 0.5}, {**GRID, "k": 0}, {**GRID, "min_range": 200.0}):
        with pytest.raises(InputError) as e:
            get_backbone("net", weights=str(weights), grid=bad)
        assert "\n" not in str(e.value)


@pytest.mark.parametrize("grid", [None, GRID])
def test_net_backbone_inside_gloam_run(tmp_path, weights, grid):
    # A folder of four scans of one scene, the sensor moving 0.3 m along x per scan.
    scene, _ = toy_scan(2, 6000)
    rng = np.random.default_rng(4)
    across = np.c_[
        np.full(1500, -7.0),
        rng.uniform(-8, 8, 1500),
        rng.uniform(-1.7, 4, 1500),
        rng.uniform(0, 1, 1500),
    ]  # a wall across x, so that x is constrained
    scene = np.concatenate([scene, across.astype(np.float32)])
    folder = tmp_path / "scans"
    folder.mkdir()
    for i in range(4):
        np.save(folder / f"{i:06d}.npy", scene - np.float32([0.3 * i, 0, 0, 0]))
    backbone = get_backbone("net", weights=str(weights), grid=grid)
    pca = fit_pca([backbone(np.load(folder / f"{i:06d}.npy")) for i in (0, 3)])
    model = init_model(jax.random.PRNGKey(0), pca, backbone="net",
                       backbone_options=backbone.options(), init="gicp")  # fmt: skip
    save_model(tmp_path / "model.npz", model)
    result = CliRunner().invoke(app, [
        "run", str(folder), "--method", "gloam", "--weights", str(tmp_path / "model.npz"),
        "--out", str(tmp_path / "results"), "--no-compilation-cache",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    poses = np.loadtxt(tmp_path / "results" / "latest" / "scans_poses_lidar_kitti.txt")
    assert poses.shape == (4, 12)
    # An untrained model that starts at plain GICP tracks the 0.3 m steps.
    np.testing.assert_allclose(poses[:, [3, 7, 11]], np.c_[0.3 * np.arange(4), [[0, 0]] * 4],
                               atol=0.03)  # fmt: skip


def test_train_backbone_resumes_to_the_same_weights(tmp_path):
    from gloam_jax.io.kitti import write_labels
    from gloam_jax.training.segmentation import train_segmentation

    root = tmp_path / "data"
    for seq, seeds in (("00", (0, 1)), ("01", (2,))):
        for i, seed in enumerate(seeds):
            scan, labels = toy_scan(seed, 1500)
            (root / "sequences" / seq / "velodyne").mkdir(parents=True, exist_ok=True)
            scan.tofile(root / "sequences" / seq / "velodyne" / f"{i:06d}.bin")
            write_labels(root / "sequences" / seq / "labels" / f"{i:06d}.label", labels)
    args = ["train-backbone", str(root), "--train", "00", "--test", "01", "--steps", "4",
            "--batch", "2", "--crop", "256", "--eval-every", "2"]  # fmt: skip
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "a")])
    assert result.exit_code == 0, result.output
    assert "held-out mIoU" in result.output and "road" in result.output
    history = json.loads((tmp_path / "a" / "history.json").read_text())
    assert [h["step"] for h in history] == [2, 4] and (tmp_path / "a" / "curve.png").is_file()

    cfg = SegmentationConfig(data=str(root), train=("00",), test=("01",), steps=4, batch=2,
                             crop=256, eval_every=2)  # fmt: skip

    def stop_after_3(label, done, total, **fields):
        if label == "training steps" and done == 3:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_segmentation(cfg, tmp_path / "b", stop_after_3)
    net, provenance = train_segmentation(cfg, tmp_path / "b")
    first, _ = load_net(tmp_path / "a" / "net.npz")
    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(net), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    assert provenance["steps"] == 4 and set(provenance["test"]["iou"]) == {"road", "building",
                                                                           "pole"}  # fmt: skip
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "b"), "--crop", "300"])
    assert result.exit_code == 2 and "started with other crop" in result.output
    # A smaller network (experiments/small_net): its shape is in its file.
    small = [*args, "--widths", "4,8,16", "--embed", "8"]
    result = CliRunner().invoke(app, [*small, "--out", str(tmp_path / "c")])
    assert result.exit_code == 0, result.output
    net, _ = load_net(tmp_path / "c" / "net.npz")
    assert (net.config.widths, net.config.embed, net.decode.weight.shape) == ((4, 8, 16), 8,
                                                                              (24, 8))  # fmt: skip
    for bad in ("8,16", "8,x,16", "8,1,16"):
        result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "d"), "--widths", bad])
        assert result.exit_code == 2 and "--widths needs three channel counts" in result.output


def test_shipped_network_loads_and_says_how_it_was_trained():
    backbone = get_backbone("net")
    assert backbone.options() == {"weights": "default"} and backbone.dim == 32
    test = backbone.provenance["test"]
    assert test["miou"] > 0.6 and test["scans"] > 0 and backbone.provenance["steps"] > 0
    assert set(test["iou"]) <= set(CLASSES)
    from gloam_jax.config import load_config
    from gloam_jax.models import load_model

    model = load_model(load_config("gloam_net").model)
    assert model.backbone_name == "net" and model.backbone().dim == model.pca.input_dim
    assert model.provenance["mode"] == "grad" and model.provenance["steps"] > 0
    # Chosen on the long validation drives, below GICP there; its network ships beside it and
    # runs on the registration's grid (experiments/net_long).
    assert model.provenance["selected_on"] == "val_long"
    assert model.provenance["selected_value"] < model.provenance["validation_gicp"] == 1.0
    beside = shipped_model_path("net").with_name("gloam_net_backbone.npz")
    assert model.backbone_options["weights"] == str(beside)
    assert model.backbone_options["grid"]["resolution"] == 0.5
    fine_tuned = load_net(beside)[1]
    assert fine_tuned["fine_tuned_from"] == "intensity-rank" and fine_tuned["layers"] == "decode"
    # The geometry-only network, by name; a training run picks it with backbone_weights.
    blind = get_backbone("net", weights="no-intensity")
    assert not blind.net.config.intensity and blind.provenance["test"]["miou"] > 0.5
    ranked = get_backbone("net", weights="intensity-rank")
    assert ranked.net.config.intensity_rank and ranked.provenance["test"]["miou"] > 0.6
    assert backbone.net.config.intensity
    from gloam_jax.training.config import TrainConfig

    experiment = Path(__file__).resolve().parents[1] / "experiments" / "net_protocol"
    picked = load_config(str(experiment / "train_protocol_net_noint_finetune.yaml"), TrainConfig)
    assert (picked.backbone, picked.backbone_weights) == ("net", "no-intensity")
    # the chain that fine-tuned the shipped net model's network (gloam_net_backbone.npz)
    picked = load_config(str(experiment / "train_protocol_net_rank_finetune.yaml"), TrainConfig)
    assert (picked.backbone, picked.backbone_weights) == ("net", "intensity-rank")
    assert picked.grad.head_learning_rate == 0.001
    with pytest.raises(InputError, match="backbone_weights chooses the net"):
        TrainConfig(backbone_weights="no-intensity")


def test_segment_labels_scans_as_semantickitti_files(sim_sequence, tmp_path):
    from gloam_jax.io import KittiSequence, read_labels

    out = tmp_path / "seg"
    args = ["segment", str(sim_sequence), "--sequence", "00", "--start", "0", "--frames", "2",
            "--stride", "20", "--out", str(out), "--preview"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    seq = KittiSequence(sim_sequence, "00")
    summary = json.loads((out / "segment.json").read_text())
    assert summary["frames"] == [0, 20] and sum(summary["share"].values()) == pytest.approx(1.0)
    # The drive has labels, so the classes are scored too: as the training's evaluate does.
    from gloam_jax.training.segmentation import evaluate

    scores = evaluate(get_backbone("net").net, str(sim_sequence), ("00",), every=20)
    assert summary["scores"]["scans"] == 2 and "mIoU" in result.output
    assert summary["scores"]["miou"] == pytest.approx(scores["miou"], abs=1e-9)
    for i in (0, 20):
        predicted = read_labels(out / "labels" / f"{i:06d}.label")
        truth = class_index(seq.labels(i))
        assert predicted.shape == truth.shape and (out / "preview" / f"{i:06d}.png").is_file()
        # The shipped network on a world it never saw (a 32-beam drive): most points right.
        known = truth >= 0
        agree = np.mean(class_index(predicted)[known] == truth[known])
        assert agree > 0.8, agree
    bad = [*args[:-3], "--out", str(tmp_path / "x"), "--weights", "no.npz"]
    result = CliRunner().invoke(app, bad)
    assert result.exit_code == 2 and "no.npz" in result.output and "Traceback" not in result.output
