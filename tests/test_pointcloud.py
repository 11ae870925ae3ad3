"""Host preprocessing: voxel grid, range crop, padding buckets."""

import numpy as np
import pytest

from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError


def reference_voxel_means(points: np.ndarray, size: float) -> dict[tuple, np.ndarray]:
    groups: dict[tuple, list] = {}
    for p in points:
        groups.setdefault(tuple(np.floor(p[:3] / size).astype(int)), []).append(p)
    return {k: np.mean(v, axis=0) for k, v in groups.items()}


def test_voxel_downsample_means_in_sorted_key_order():
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-30, 30, (5000, 3)), rng.uniform(0, 1, 5000)])
    out = pc.voxel_downsample(points, 2.0)
    ref = reference_voxel_means(points, 2.0)
    assert out.shape == (len(ref), 4)
    keys = sorted(ref)  # lexicographic (x, y, z)
    np.testing.assert_allclose(out, np.stack([ref[k] for k in keys]), atol=1e-12)
    inverse, counts = pc.voxel_index(points, 2.0)
    assert counts.sum() == len(points) and len(counts) == len(ref)
    # Each point's voxel index names the row holding its mean.
    np.testing.assert_allclose(out[inverse[:10], :3] // 2.0, points[:10, :3] // 2.0)


def test_voxel_downsample_far_from_the_origin_and_on_cell_borders():
    # A large (UTM-like) offset, and points exactly on voxel borders (floor, not truncation).
    points = np.array([[5e5, -4e6, 10.0], [5e5 + 0.49, -4e6 + 0.2, 10.1], [-0.5, -0.5, 0.0],
                       [-0.0001, 0.0, 0.0], [0.0, 0.0, 0.0]])  # fmt: skip
    out = pc.voxel_downsample(points, 0.5)
    assert len(out) == 4
    np.testing.assert_allclose(out[0], [-0.5, -0.5, 0.0])
    np.testing.assert_allclose(out[2], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(out[3], [5e5 + 0.245, -4e6 + 0.1, 10.05])


def test_voxel_downsample_rejects_bad_points_and_passes_through_size_zero():
    points = np.random.default_rng(1).normal(size=(10, 3))
    np.testing.assert_array_equal(pc.voxel_downsample(points, 0.0), points)
    with pytest.raises(ValueError, match="NaN"):
        pc.voxel_downsample(np.vstack([points, [np.nan, 0, 0]]), 0.5)
    with pytest.raises(InputError, match="too far apart to voxelise"):
        pc.voxel_downsample(np.array([[-1e12, -1e12, -1e12], [1e12, 1e12, 1e12]]), 0.01)


def test_range_mask_and_buckets():
    scan = np.array([[1.0, 0, 0], [5.0, 0, 0], [np.nan, 0, 0], [200.0, 0, 0]])
    keep, invalid = pc.range_mask(scan, 3.0, 100.0)
    assert keep.tolist() == [False, True, False, False] and invalid == 1
    with pytest.raises(InputError, match="NaN, infinite or beyond"):
        pc.range_mask(np.full((3, 3), np.inf), 3.0, 100.0)


def test_range_band_selects_the_mask_rows_in_float64():
    rows = [[1.0, 0, 0, 7], [5.0, 0, 0, 8], [np.nan, 0, 0, 9], [0, 4.0, 1, 10]]
    scan = np.array(rows, np.float32)
    band = pc.range_band(scan, 3.0, 100.0, "scan.bin")
    assert band.keep.tolist() == [False, True, False, True] and band.invalid == 1
    assert band.xyz.dtype == np.float64
    np.testing.assert_array_equal(band.xyz, [[5, 0, 0], [0, 4, 1]])
    np.testing.assert_array_equal(band.intensity(), [8, 10])
    assert pc.range_band(scan[:, :3], 3.0, 100.0).intensity() is None
    assert len(pc.range_band(scan, 50.0, 100.0).xyz) == 0
    with pytest.raises(InputError, match="scan.bin.*NaN, infinite or beyond"):
        pc.range_band(np.full((3, 3), np.nan), 3.0, 100.0, "scan.bin")


def test_huge_coordinates_are_invalid_points_not_overflows():
    """1e30 is no measurement: dropped and counted like NaN, not squared into inf (float32)."""
    scan = np.array([[5.0, 0, 0], [1e30, 0, 0], [0, 1e9, 0], [0, 3e4, 0]], np.float32)
    keep, invalid = pc.range_mask(scan, 3.0, 1e5)
    assert keep.tolist() == [True, False, False, True] and invalid == 2
    kept, dropped = pc.drop_invalid(scan)
    assert len(kept) == 2 and dropped == 2
    with pytest.raises(InputError, match="all 2 points are NaN, infinite or beyond"):
        pc.drop_invalid(np.full((2, 3), 1e30, np.float32))


def test_prepare_drops_a_far_outlier():
    import gloam_jax

    rng = np.random.default_rng(0)
    points = rng.uniform(-10, 10, size=(3000, 3))
    points[:, 2] = np.where(rng.random(3000) < 0.5, 0.0, points[:, 2])
    source = points.copy()
    source[7] = 1e30
    result = gloam_jax.prepare(source, downsampling_resolution=0.5)
    assert result.num_dropped == 1
    assert pc.bucket_size(1000) == 1024 and pc.bucket_size(1025) == 1280
    sticky = pc.StickyBuckets()
    assert sticky.floor("source") == 0
    assert sticky("source", 1000) == pc.bucket_size(1200) == 1280
    assert sticky("source", 500) == sticky("source", 1100) == 1280  # never shrinks
    assert sticky("source", 5000) == pc.bucket_size(6000) == 6144  # grows, 20 % headroom
    assert sticky("source", 1000) == sticky.floor("source") == 6144  # and stays there
    restored = pc.StickyBuckets()
    restored.restore(sticky.state())
    assert restored("source", 6000) == 6144 and restored.floor("other") == 0
    padded, mask = pc.pad(np.ones((3, 2)), 5)
    assert padded.shape == (5, 2) and mask.tolist() == [True] * 3 + [False] * 2


def test_voxel_means_of_several_arrays_keep_their_dtypes():
    rng = np.random.default_rng(2)
    points = rng.uniform(-10, 10, (3000, 3))
    features = rng.normal(size=(3000, 6)).astype(np.float32)
    xyz, feats = pc.voxel_means(points, 1.5, [points, features])
    assert feats.dtype == np.float32 and len(xyz) == len(feats)
    both = pc.voxel_downsample(np.column_stack([points, features]), 1.5)
    np.testing.assert_allclose(xyz, both[:, :3], atol=1e-12)
    np.testing.assert_allclose(feats, both[:, 3:], atol=1e-5)


def test_voxel_keys_name_world_voxels_across_clouds():
    a = np.array([[0.1, 0.1, 0.1], [0.6, -0.1, 0.0], [-1000.2, 3.3, 7.9]])
    b = a + 0.3  # moves the first point within its 0.5 m voxel, the others out of theirs
    ka, kb = pc.voxel_keys(a, 0.5), pc.voxel_keys(b, 0.5)
    assert ka.dtype == np.int64 and ka[0] == kb[0] and (ka[1:] != kb[1:]).all()
    assert len(set(ka.tolist())) == 3
    # keys of cells differing in one axis only differ
    cells = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0]]) * 0.5 + 0.25
    assert len(set(pc.voxel_keys(cells, 0.5).tolist())) == 5
    with pytest.raises(ValueError, match="km from the origin"):
        pc.voxel_keys(np.array([[6e5, 0.0, 0.0]]), 0.5)
