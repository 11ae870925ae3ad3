"""The four methods (gicp, gicp_da, gicp_ce, gloam): learned parts inside registration and
odometry, model files on the command line, and their errors."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from gloam_jax import io
from gloam_jax.cli import app
from gloam_jax.errors import InputError
from gloam_jax.features import fit_pca, get_backbone
from gloam_jax.features.novelty import fit_novelty
from gloam_jax.gicp import GICPConfig
from gloam_jax.models import init_model, learned_parts, load_model, save_model
from gloam_jax.neighbors import KdTree
from gloam_jax.odometry import Odometry, OdometryConfig
from gloam_jax.registration import align_prepared, build_cloud


@pytest.fixture(scope="module")
def model(sim_sequence):
    seq = io.KittiSequence(sim_sequence, "00")
    backbone = get_backbone("geometric")
    pca = fit_pca([backbone(seq.scan(i)) for i in (0, 20)])
    return init_model(jax.random.PRNGKey(0), pca, backbone_options=backbone.options())


def _scene(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Floor, two walls and a pole, with made-up per-point features (N, 6)."""
    rng = np.random.default_rng(seed)
    k = 1500
    floor = np.c_[rng.uniform(-10, 10, (k, 2)), np.zeros(k)]
    wall_x = np.c_[np.full(k, 6.0), rng.uniform(-10, 10, k), rng.uniform(0, 4, k)]
    wall_y = np.c_[rng.uniform(-10, 10, k), np.full(k, -5.0), rng.uniform(0, 4, k)]
    a = rng.uniform(0, 2 * np.pi, 300)
    pole = np.c_[2 + 0.1 * np.cos(a), 1 + 0.1 * np.sin(a), rng.uniform(0, 4, 300)]
    points = np.concatenate([floor, wall_x, wall_y, pole]) + rng.normal(0, 0.003, (4800, 3))
    return points, rng.normal(size=(len(points), 6))


def _register(model, method: str, T_true: np.ndarray) -> np.ndarray:
    target_points, target_features = _scene(0)
    source_points = (target_points - T_true[:3, 3]) @ T_true[:3, :3]
    learned = learned_parts(model, method)
    kw = dict(num_neighbors=10, pca_features=target_features, learned=learned)
    target = build_cloud(target_points, **kw)
    source = build_cloud(source_points, **kw)
    config = GICPConfig(num_candidates=5)
    return align_prepared(target, source, None, config).T_target_source


T_TRUE = np.array(
    [[np.cos(0.03), -np.sin(0.03), 0, 0.25], [np.sin(0.03), np.cos(0.03), 0, -0.15],
     [0, 0, 1, 0.05], [0, 0, 0, 1]]
)  # fmt: skip


def test_association_on_zero_features_is_plain_gicp(model):
    zero = model.conversion._replace(w2=jnp.zeros_like(model.conversion.w2), b2=jnp.zeros(3))
    silent = dataclasses.replace(model, conversion=zero)
    plain = _register(None, "gicp", T_TRUE)
    # Zero features add exactly 0 to every candidate's cost (the same associations), but F = 3
    # against F = 0 compiles another program: float32 ulps of the pose (ulp(0.25) = 3e-8); a
    # different association would move it by far more than 1e-6.
    np.testing.assert_allclose(_register(silent, "gicp_da", T_TRUE), plain, rtol=0, atol=1e-6)
    np.testing.assert_allclose(plain, T_TRUE, atol=5e-3)


def test_learned_plane_eigenvalues_give_plain_gicp(model):
    # A constant (1, eps, 1) output becomes (eps, 1, 1) / |.|: GICP's plane covariances up to
    # one common scale, which leaves the optimum where it was.
    eps = model.eps
    flat = model.eigenvalue._replace(
        w2=jnp.zeros_like(model.eigenvalue.w2), b2=jnp.array([1.0, eps, 1.0])
    )
    planes = dataclasses.replace(model, eigenvalue=flat)
    np.testing.assert_allclose(
        _register(planes, "gicp_ce", T_TRUE), _register(None, "gicp", T_TRUE), atol=2e-4
    )


def test_the_gicp_start_registers_as_plain_gicp(model):
    # Training's start (init "gicp") is GICP itself, so a model chosen against it on validation
    # can always fall back to it.
    start = init_model(jax.random.PRNGKey(1), model.pca, init="gicp")
    np.testing.assert_allclose(
        _register(start, "gloam", T_TRUE), _register(None, "gicp", T_TRUE), atol=1e-5
    )


def test_clamped_features_register_as_the_model_on_the_clamped_features(model):
    # The novelty (gloam_jax.features.novelty) changes what the MLPs see, nothing else: a
    # region that holds every point changes nothing, one that holds none registers as the
    # model given the clamped features.
    points, features = _scene(0)
    tight = fit_novelty(features * 1e-3)  # the scene's features lie far beyond it
    loose = fit_novelty(features)._replace(radius2=1e9)

    def cloud(m, f=features):
        return build_cloud(points, 10, pca_features=f, learned=learned_parts(m, "gloam"))

    learned = cloud(model)
    clamped = np.asarray(tight.clamp(jnp.asarray(features, jnp.float32)))
    gated, expected = cloud(dataclasses.replace(model, novelty=tight)), cloud(model, clamped)
    np.testing.assert_allclose(gated.covs, expected.covs, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(gated.features, expected.features, rtol=1e-4, atol=1e-6)
    assert np.abs(gated.covs - learned.covs).max() > 1e-2
    same = cloud(dataclasses.replace(model, novelty=loose))
    np.testing.assert_array_equal(same.covs, learned.covs)
    np.testing.assert_array_equal(same.features, learned.features)


def test_a_fallback_model_runs_gicps_own_path_bit_for_bit(sim_sequence, model):
    # Training's fall-back exports the learned parts set to register as GICP (as_gicp):
    # odometry must then be GICP exactly (not up to the 1/sqrt(2) covariance scale), and
    # needs no features.
    parts = model.learned.as_gicp()
    fallback = dataclasses.replace(model, conversion=parts.conversion, eigenvalue=parts.eigenvalue)
    seq = io.KittiSequence(sim_sequence, "00")
    runs = {}
    # gloam's association candidates (5 in gloam.yaml) serve the learned association only.
    for method, m, k in (("gicp", None, 1), ("gloam", fallback, 5)):
        odometry = Odometry(OdometryConfig(method=method, gicp=GICPConfig(num_candidates=k)), m)
        assert odometry.config.gicp.num_candidates == 1
        assert not odometry.needs_features
        for i in range(4):
            odometry.register_frame(seq.scan(i), seq.point_times(i), 0.1)
        runs[method] = np.stack(odometry.poses)
    # Bit for bit is the contract: the fallback takes GICP's own code path (one candidate, no
    # features), the same compiled programs on the same scans.
    np.testing.assert_array_equal(runs["gloam"], runs["gicp"])
    # Anything else stays learned: an eigenvalue output off the plane, a live conversion MLP.
    off = parts.eigenvalue._replace(b2=parts.eigenvalue.b2.at[1].set(0.9))
    assert Odometry(OdometryConfig(method="gloam"),
                    dataclasses.replace(fallback, eigenvalue=off)).needs_features  # fmt: skip
    live = Odometry(
        OdometryConfig(method="gloam"), dataclasses.replace(fallback, conversion=model.conversion)
    )
    assert live.learned.conversion is not None and live.learned.eigenvalue is None


@pytest.mark.parametrize("method", ["gicp_da", "gicp_ce", "gloam"])
def test_learned_methods_track_a_simulated_drive(sim_sequence, model, method):
    seq = io.KittiSequence(sim_sequence, "00")
    config = OdometryConfig(method=method, gicp=GICPConfig(num_candidates=5))
    odometry = Odometry(config, model)
    backbone = get_backbone("geometric")
    for i in range(8):
        scan = seq.scan(i)
        odometry.register_frame(scan, seq.point_times(i), 0.1, features=backbone(scan))
    assert not any(s.error for s in odometry.status)
    # Untrained MLPs: the estimate must stay sane, not better than GICP.
    gt = seq.gt_poses_lidar
    drift = np.linalg.inv(gt[0]) @ gt[7] @ np.linalg.inv(odometry.poses[7])
    assert np.linalg.norm(drift[:3, 3]) < 0.5


def test_a_model_on_the_voxel_grid_registers_raw_scans_as_with_per_point_features(
    sim_sequence, tmp_path
):
    """A backbone with the preprocessing's voxels and range band makes the features with the
    voxel centres (Odometry.grid_backbone): register_frame needs none, the poses are within
    millimetres of those of per-point features (the covariances then take the backbone's
    neighbourhoods, found before the deskew), the frame's features stage is timed apart from
    its voxels, and model-info says where the features are made."""
    seq = io.KittiSequence(sim_sequence, "00")
    backbone = get_backbone("geometric", voxel_size=0.5, scales=[10], min_range=3.0,
                            max_range=100.0)  # fmt: skip
    pca = fit_pca([backbone(seq.scan(i)) for i in (0, 20)])
    model = init_model(jax.random.PRNGKey(1), pca, backbone_options=backbone.options())
    config = OdometryConfig(method="gloam", gicp=GICPConfig(num_candidates=5))
    grid, per_point = Odometry(config, model), Odometry(config, model)
    assert grid.grid_backbone is not None
    for i in range(5):
        scan, times = seq.scan(i), seq.point_times(i)
        grid.register_frame(scan, times, 0.1)
        per_point.register_frame(scan, times, 0.1, features=backbone(scan))
    assert not any(s.error for s in grid.status)
    np.testing.assert_allclose(np.stack(grid.poses), np.stack(per_point.poses), atol=5e-3)
    stages = grid.status[-1].stage_ms
    assert stages["features"] > 0 and stages["voxels"] > 0
    assert per_point.status[-1].stage_ms["features"] == 0
    save_model(tmp_path / "grid.npz", model)
    for file, on_grid in ((tmp_path / "grid.npz", True), (None, False)):
        shown = CliRunner().invoke(app, ["model-info"] + ([str(file)] if file else []))
        assert shown.exit_code == 0
        assert ("features: made on the odometry's voxel grid" in shown.output) == on_grid


def test_the_grid_backbone_s_neighbours_serve_the_covariances(sim_sequence):
    """The grid backbone's k-NN of the voxel centres (found before the deskew, nearest first)
    comes with the centres, cut to num_neighbors, and the covariances take it instead of a
    second query: the same covariances as a query of those centres; a backbone whose largest
    scale is below num_neighbors, or a method without features, leaves the query to the
    registration; neighbours of another shape are refused."""
    seq = io.KittiSequence(sim_sequence, "00")
    scan, times = seq.scan(3), seq.point_times(3)
    config = OdometryConfig(method="gloam", gicp=GICPConfig(num_candidates=5))
    k = config.preprocess.num_neighbors

    def odometry(scales: list[int]) -> Odometry:
        backbone = get_backbone("geometric", voxel_size=0.5, scales=scales, min_range=3.0,
                                max_range=100.0)  # fmt: skip
        pca = fit_pca([backbone(scan)])
        return Odometry(config, init_model(jax.random.PRNGKey(1), pca,
                                           backbone_options=backbone.options()))  # fmt: skip

    centres = odometry([10, 30]).voxel_centres(scan, times)
    points = centres.points
    assert centres.neighbours.shape == (len(points), k) and centres.neighbours.dtype == np.int32
    np.testing.assert_array_equal(centres.neighbours, KdTree(points).query(points, k)[0])
    given = build_cloud(points, k, neighbours=centres.neighbours)
    np.testing.assert_array_equal(given.covs, build_cloud(points, k).covs)
    with pytest.raises(ValueError, match="neighbours"):
        build_cloud(points, k, neighbours=centres.neighbours[:, :5])
    assert odometry([5]).voxel_centres(scan, times).neighbours is None
    assert Odometry(OdometryConfig()).voxel_centres(scan, times).neighbours is None


def test_learned_methods_need_a_model_and_features(sim_sequence, model):
    with pytest.raises(InputError, match="method 'gloam' needs a model file"):
        Odometry(OdometryConfig(method="gloam"))
    odometry = Odometry(OdometryConfig(method="gloam"), model)
    scan = io.KittiSequence(sim_sequence, "00").scan(0)
    with pytest.raises(InputError, match="a.bin: method 'gloam' needs per-point features"):
        odometry.register_frame(scan, source="a.bin")
    odometry.register_frame(scan, source="b.bin", features=np.zeros((10, 20)))
    assert "b.bin: features have 10 rows but the scan has" in odometry.status[-1].error


def test_init_model_then_run_gloam_from_the_command_line(sim_sequence, tmp_path):
    runner = CliRunner()
    weights = tmp_path / "model.npz"
    made = runner.invoke(
        app,
        ["init-model", str(sim_sequence), "00", "--every", "20", "--backbone-options",
         "{drop: [density], max_height: 4.0}", "--out", str(weights)],
    )  # fmt: skip
    assert made.exit_code == 0, made.output
    assert "of the variance" in made.output and weights.exists()
    # The run below rebuilds that backbone from the file: 19 features, not 20.
    assert load_model(weights).backbone().options()["drop"] == ["density"]
    assert load_model(weights).pca.mean.shape == (19,)
    for bad in ("[density]", "{drop: [density]"):
        refused = runner.invoke(app, ["init-model", str(sim_sequence), "00", "--backbone-options",
                                      bad, "--out", str(tmp_path / "bad.npz")])  # fmt: skip
        assert refused.exit_code == 2, refused.output
        assert "--backbone-options must be a YAML mapping" in refused.output
    result = runner.invoke(
        app,
        ["run", str(sim_sequence), "--sequence", "00", "--frames", "5", "--config",
         "configs/gloam.yaml", "--weights", str(weights), "--out", str(tmp_path / "runs")],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    assert len(io.read_kitti_poses(tmp_path / "runs" / "latest" / "00_poses_kitti.txt")) == 5
    no_model = tmp_path / "no_model.yaml"
    no_model.write_text("method: gloam\nmodel: null\n")
    missing = runner.invoke(
        app, ["run", str(sim_sequence), "--config", str(no_model), "--frames", "3",
              "--out", str(tmp_path / "failed")],
    )  # fmt: skip
    assert missing.exit_code == 2 and "needs a model file" in missing.output
    assert not (tmp_path / "failed").exists()


def test_saved_model_runs_identically(tmp_path, sim_sequence, model):
    save_model(tmp_path / "m.npz", model)
    config = OdometryConfig(method="gloam", model=str(tmp_path / "m.npz"))
    seq = io.KittiSequence(sim_sequence, "00")
    features = get_backbone("geometric")(seq.scan(0))
    a, b = Odometry(config), Odometry(dataclasses.replace(config, model=None), model)
    for odo in (a, b):
        odo.register_frame(seq.scan(0), features=features)
        odo.register_frame(seq.scan(1), features=get_backbone("geometric")(seq.scan(1)))
    # Bit for bit: the file holds the same weights (float32 and float64 .npz are lossless), run
    # through the same compiled programs on the same scans in this process.
    np.testing.assert_array_equal(a.poses[-1], b.poses[-1])
