"""Feature backbones (geometric, precomputed) and the frozen PCA."""

import jax.numpy as jnp
import numpy as np
import pytest
from sklearn.decomposition import PCA

from gloam_jax.errors import InputError
from gloam_jax.features import (
    FeaturePCA,
    GeometricBackbone,
    PrecomputedBackbone,
    fit_pca,
    get_backbone,
    intensity_warning,
)
from gloam_jax.features import geometric as geo_features
from gloam_jax.models import shipped_model_path


def synthetic_scan(seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Ground plane, a wall, a pole and a noise blob, with intensity: (N, 4) and part masks."""
    rng = np.random.default_rng(seed)
    g = rng.uniform(-10, 10, (6000, 2))
    ground = np.c_[g, 0.002 * rng.normal(size=len(g))]
    w = np.c_[rng.uniform(-8, 8, 2500), rng.uniform(0, 4, 2500)]
    wall = np.c_[np.full(len(w), 9.0) + 0.002 * rng.normal(size=len(w)), w]
    z = rng.uniform(0.5, 6.0, 600)
    pole = np.c_[np.full(600, -4.0), np.full(600, 3.0), z] + 0.003 * rng.normal(size=(600, 3))
    blob = np.array([3.0, -5.0, 1.5]) + 0.4 * rng.normal(size=(800, 3))
    parts = [ground, wall, pole, blob]
    xyz = np.concatenate(parts)
    scan = np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32)
    bounds = np.cumsum([0] + [len(p) for p in parts])
    masks = {}
    for name, lo, hi in zip(
        ("ground", "wall", "pole", "blob"), bounds[:-1], bounds[1:], strict=True
    ):
        masks[name] = np.zeros(len(xyz), bool)
        masks[name][lo:hi] = True
    return scan, masks


@pytest.fixture(scope="module")
def scan_features():
    scan, masks = synthetic_scan()
    backbone = GeometricBackbone()
    return scan, masks, backbone, backbone(scan)


def column(backbone, features, name):
    return features[:, backbone.feature_names.index(name)]


def test_geometric_shape_finite_deterministic(scan_features):
    scan, _, backbone, f = scan_features
    assert f.shape == (len(scan), 20) == (len(scan), backbone.dim)
    assert f.dtype == np.float32
    assert np.all(np.isfinite(f))
    np.testing.assert_array_equal(backbone(scan), f)
    # Every column roughly unit-scaled: no column dominates by its units.
    assert np.all(np.abs(f) <= 4.0)


def test_geometric_features_discriminate(scan_features):
    _, masks, bb, f = scan_features
    inner = masks["ground"] & (np.abs(scan_features[0][:, :2]).max(axis=1) < 7)
    med = {
        (name, part): float(np.median(column(bb, f, name)[mask]))
        for name in bb.feature_names
        for part, mask in (*masks.items(), ("inner", inner))
    }
    # Planes: planar, not scattered, the wall vertical and the road horizontal (k = 10 on a
    # random planar patch gives only ~0.5: few points, elongated by chance).
    for part in ("inner", "wall"):
        assert med["planarity_k30", part] > 0.6 > med["linearity_k30", part] + 0.2
        assert med["planarity_k10", part] > 3 * med["planarity_k10", "pole"] + 0.3
        assert med["scattering_k30", part] < 0.01
    assert med["verticality_k30", "wall"] > 0.9 and med["verticality_k30", "inner"] < 0.1
    # The pole is a line, the blob a volume.
    assert med["linearity_k10", "pole"] > 0.9 and med["linearity_k30", "pole"] > 0.9
    assert med["scattering_k30", "blob"] > 0.4 and med["omnivariance_k30", "blob"] > 0.9
    # Height above the local ground: ~0 on the road, metres on the pole top.
    height = column(bb, f, "height") * 5.0
    assert np.abs(np.median(height[inner])) < 0.05
    top = masks["pole"] & (scan_features[0][:, 2] > 5.0)
    assert np.median(height[top]) > 4.5


def test_geometric_nan_rows_degenerate_scans_and_no_intensity():
    scan, _ = synthetic_scan(1)
    backbone = GeometricBackbone()
    with_nan = scan.copy()
    with_nan[[5, 100]] = np.nan
    f = backbone(with_nan)
    assert np.all(f[[5, 100]] == 0) and np.all(np.isfinite(f))
    keep = np.ones(len(scan), bool)
    keep[[5, 100]] = False
    np.testing.assert_array_equal(f[keep], backbone(with_nan[keep]))

    f3 = backbone(scan[:, :3])
    assert np.all(column(backbone, f3, "intensity") == 0)
    line = np.c_[np.linspace(0, 5, 50), np.zeros(50), np.zeros(50)]  # exactly collinear
    for tiny in (
        scan[:1, :3],
        np.repeat(scan[:1, :3], 7, 0),
        scan[:4],
        line,
        np.full((3, 4), np.nan),
    ):
        out = backbone(tiny)
        assert out.shape == (len(tiny), 20) and np.all(np.isfinite(out))
    with pytest.raises(InputError, match="expected an"):
        backbone(np.zeros((10, 2)))


def test_height_cap_and_dropped_features(scan_features):
    scan, masks, bb, f = scan_features
    capped = GeometricBackbone(max_height=2.0, drop=["density", "intensity"])
    g = capped(scan)
    assert capped.feature_names == tuple(
        n for n in bb.feature_names if n not in ("density", "intensity")
    )
    assert g.shape == (len(scan), 18) == (len(scan), capped.dim)
    # Every kept column is the full backbone's, bit for bit, but the height, which stops at
    # the cap: the pole's top (5-6 m above the road) reads 2 m, the road stays at ~0.
    for name in capped.feature_names:
        if name != "height":
            np.testing.assert_array_equal(column(capped, g, name), column(bb, f, name))
    height, full = column(capped, g, "height") * 5.0, column(bb, f, "height") * 5.0
    np.testing.assert_allclose(height, np.minimum(full, 2.0), atol=1e-6)
    top = masks["pole"] & (scan[:, 2] > 5.0)
    assert np.all(np.abs(height[top] - 2.0) < 1e-6)
    # No intensity column: the model keeps no fitted intensity to compare scans with.
    assert capped.fitted_intensity(fit_pca(g, 6)) is None
    rebuilt = get_backbone(capped.name, **capped.options())
    np.testing.assert_array_equal(rebuilt(scan), g)
    with pytest.raises(InputError, match="drop naming some of its features"):
        GeometricBackbone(drop=["colour"])
    with pytest.raises(InputError, match="max_height > 0"):
        GeometricBackbone(max_height=0.0)


def test_closed_form_eigen_against_numpy():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(500, 3, 3)) * rng.uniform(0.01, 10, (500, 1, 1))
    C = A @ A.transpose(0, 2, 1)
    C[:50] = np.diag([2.0, 1e-9, 1e-9])  # a line: two (near-)repeated eigenvalues
    packed = C[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]
    values, vectors = np.linalg.eigh(C)
    lam = geo_features._eigenvalues(packed)
    np.testing.assert_allclose(lam, values[:, ::-1], atol=1e-12 * values.max())
    nz = geo_features._normal_z(packed[50:], values[50:, 0])
    np.testing.assert_allclose(nz, np.abs(vectors[50:, 2, 0]), atol=1e-9)


def test_backbone_registry():
    bb = get_backbone("geometric", voxel_size=0.3, scales=[8, 16])
    assert bb.dim == 20 and bb.options()["scales"] == [8, 16]
    assert get_backbone(bb.name, **bb.options()).options() == bb.options()
    with pytest.raises(InputError, match="unknown backbone 'pointnet'"):
        get_backbone("pointnet")
    with pytest.raises(InputError, match="backbone 'geometric'"):
        get_backbone("geometric", radius=2.0)
    with pytest.raises(InputError, match="increasing scales"):
        get_backbone("geometric", scales=[30, 10])


def test_precomputed_reads_npy_and_txt(tmp_path):
    scan = np.zeros((5, 4), np.float32)
    feats = np.arange(15, dtype=np.float64).reshape(5, 3)
    np.save(tmp_path / "000007.npy", feats)
    np.savetxt(tmp_path / "scan_b.txt", feats + 1)
    bb = get_backbone("precomputed", folder=str(tmp_path))
    out = bb(scan, path="/data/velodyne/000007.bin")
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, feats)
    np.testing.assert_array_equal(bb(scan, frame=7), feats)
    np.testing.assert_array_equal(bb(scan, path="scan_b.pcd"), feats + 1)


def test_precomputed_errors(tmp_path):
    bb = PrecomputedBackbone(tmp_path)
    scan = np.zeros((5, 4), np.float32)
    np.save(tmp_path / "000001.npy", np.zeros((4, 3)))
    with pytest.raises(InputError) as e:
        bb(scan, frame=1)
    message = str(e.value)
    assert "000001.npy" in message and "4 feature rows" in message and "5 points" in message
    assert "\n" not in message
    with pytest.raises(InputError, match="000002.npy: feature file not found"):
        bb(scan, frame=2)
    np.save(tmp_path / "000003.npy", np.zeros(5))
    with pytest.raises(InputError, match=r"000003.npy: expected an \(N, D\)"):
        bb(scan, frame=3)
    bad = np.zeros((5, 3))
    bad[2, 1] = np.nan
    np.save(tmp_path / "000004.npy", bad)
    with pytest.raises(InputError, match="000004.npy: .*NaN or infinite values .*row 2"):
        bb(scan, frame=4)
    (tmp_path / "000005.npy").write_bytes(b"not an array")
    with pytest.raises(InputError, match="000005.npy: cannot read features"):
        bb(scan, frame=5)
    with pytest.raises(InputError, match="scan path or frame"):
        bb(scan)


def test_pca_matches_sklearn_and_is_frozen(scan_features):
    _, _, _, f = scan_features
    halves = [f[::2], f[1::2]]
    pca = fit_pca(halves, 6)
    assert isinstance(pca, FeaturePCA) and pca.components.shape == (6, 20)
    explained = float(pca.explained_variance_ratio.sum())
    assert 0.5 < explained <= 1.0
    # Same projection as scikit-learn on the standardised rows.
    x = np.concatenate(halves).astype(np.float64)
    std = np.where(x.std(0) > 1e-6, x.std(0), 1.0)
    z = (x - x.mean(0)) / std
    reference = PCA(6, svd_solver="full").fit(z).transform(z)
    np.testing.assert_allclose(pca.transform(x), reference, atol=1e-8)
    # Frozen: the same transform in float32 NumPy and JAX, and the fit is deterministic.
    np.testing.assert_allclose(
        np.asarray(pca.transform(jnp.asarray(f))), pca.transform(f), rtol=1e-5, atol=1e-5
    )
    np.testing.assert_array_equal(fit_pca(halves, 6).components, pca.components)
    # Subsampling rows keeps the same subspace, roughly.
    sub = fit_pca(f, 6, max_rows=5000)
    overlap = np.linalg.svd(sub.components @ pca.components.T, compute_uv=False)
    assert overlap.min() > 0.7


def test_pca_errors():
    with pytest.raises(InputError, match="differ in width"):
        fit_pca([np.zeros((10, 4)), np.zeros((10, 5))])
    with pytest.raises(InputError, match="at least 6 rows and columns"):
        fit_pca(np.random.default_rng(0).normal(size=(100, 4)))


def test_a_scan_in_other_intensity_units_is_flagged(scan_features, tmp_path):
    scan, _, backbone, features = scan_features  # intensity uniform in [0, 1]: mean 0.5
    pca = fit_pca([features])
    assert backbone.fitted_intensity(pca) == pytest.approx(0.5, abs=0.02)
    assert intensity_warning(backbone, pca, scan) is None
    counts = scan.copy()
    counts[:, 3] *= 255  # the same scan, intensity in 0-255
    assert "mean intensity is 128, but" in intensity_warning(backbone, pca, counts)
    assert "carry no intensity" in intensity_warning(backbone, pca, scan[:, :3])
    blind = GeometricBackbone(intensity_scale=0.0)
    assert intensity_warning(blind, fit_pca([blind(scan)]), counts) is None
    # The net's reference is its training points' mean, from its weight file.
    assert get_backbone("net").fitted_intensity() == pytest.approx(0.193, abs=1e-3)
    assert get_backbone("net", weights="no-intensity").fitted_intensity() is None

    from typer.testing import CliRunner

    from gloam_jax.cli import app

    folder = tmp_path / "scans"
    folder.mkdir()
    for i in range(2):  # the shipped model (geometric backbone) on scans in 0-255 units
        np.save(folder / f"{i:06d}.npy", counts - np.float32([0.2 * i, 0, 0, 0]))
    # Named by its file, so that it runs on this small scan, which is no sensor it knows.
    result = CliRunner().invoke(app, ["run", str(folder), "--method", "gloam", "--weights",
                                      str(shipped_model_path()), "--out", str(tmp_path / "res"),
                                      "--no-compilation-cache"])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert result.output.count("warning: the scans' mean intensity") == 1
    assert result.output.count("warning: model") == 1 and "forced" in result.output


def test_features_on_the_preprocessings_grid_are_the_per_point_path():
    """A backbone with the preprocessing's voxels and range band gives each voxel centre the
    mean of its points' features without a row per point: the same centres and PCA features
    as averaging backbone(scan) (real KITTI scan); other settings do not share the grid."""
    from shared_data import shared_path

    from gloam_jax.preprocess import PreprocessConfig, on_grid, voxel_centres
    from gloam_jax.timing import StageTimer

    scan = np.fromfile(shared_path("real_kitti16/000003.bin"), np.float32).reshape(-1, 4)
    config = PreprocessConfig()  # 0.5 m voxels over 3-100 m
    bb = GeometricBackbone(voxel_size=0.5, scales=[10], min_range=3.0, max_range=100.0)
    assert on_grid(bb, config) is bb
    for other in (GeometricBackbone(), GeometricBackbone(voxel_size=0.5, scales=[10])):
        assert on_grid(other, config) is None
    per_point = bb(scan)
    r = np.linalg.norm(scan[:, :3].astype(np.float64), axis=1)
    assert not per_point[(r < 3) | (r > 100)].any() and per_point[(r > 3) & (r < 100)].any()
    pca = fit_pca(per_point[r > 3], 6)
    slow = voxel_centres(scan, None, config, pca=pca, features=per_point)
    timer = StageTimer()
    fast = voxel_centres(scan, None, config, pca=pca, backbone=bb, timer=timer)
    np.testing.assert_array_equal(fast.points, slow.points)
    np.testing.assert_array_equal(fast.times, slow.times)
    assert fast.features.shape == slow.features.shape == (len(slow.points), 6)
    np.testing.assert_allclose(fast.features, slow.features, atol=2e-5)
    assert timer.ms["features"] > 0
    with pytest.raises(InputError, match="min_range < max_range"):
        GeometricBackbone(min_range=5.0, max_range=3.0)
