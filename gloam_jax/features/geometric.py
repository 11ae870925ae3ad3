"""Geometric backbone: multi-scale local shape descriptors, on the host in NumPy.

The scan is averaged on a fine voxel grid (``voxel_size``, 0.25 m). Each voxel gets the
eigenvalue descriptors of its k nearest voxels at every scale in ``scales`` (k = 10 and 30:
k-NN scales follow the density, which falls with range; one k-d tree query at the largest k
serves all of them) and each raw point the descriptors of its voxel. Height above the local
ground, range and intensity are per raw point.

Per scale, with eigenvalues ``l1 >= l2 >= l3`` of the neighbourhood covariance and
``e_i = l_i / (l1 + l2 + l3)`` (Weinmann et al., 2015; Hackel et al., 2016): linearity
``(e1 - e2) / e1``, planarity ``(e2 - e3) / e1``, scattering ``e3 / e1``, omnivariance
``3 (e1 e2 e3)^(1/3)``, anisotropy ``(e1 - e3) / e1``, eigenentropy ``-sum e_i ln e_i / ln 3``,
change of curvature ``3 e3`` and verticality ``1 - |n_z|`` (n the normal): all in [0, 1].
Then height above the lowest voxel within +-3 m horizontally (/ 5 m, clipped to
[-5 m, ``max_height``]), the log10 density of raw points in the largest-k neighbourhood (/ 3),
range (/ 50 m) and intensity (times ``intensity_scale``). Every column spans about one unit,
so none dominates a PCA by its units.

Two of them describe the sensor as much as the scene: point density follows the beam count,
and height above the ground how far up a sensor looks (a VLP-16 sees facades at 10 m, an
HDL-64 rarely above 4 m). ``max_height`` and ``drop`` (feature names left out) make features
that a sensor missing from training shifts less (experiments/invariant_features).

``min_range`` and ``max_range`` keep only points in that band (the others get zero rows).
With the preprocessing's voxel size and band the backbone shares its grid
(:meth:`GeometricBackbone.shares_grid`): :meth:`GeometricBackbone.voxel_features` then gives
each voxel centre the mean of its points' rows directly, without a second grid or a row per
point (``Odometry.grid_backbone``; experiments/grid_features).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from scipy import ndimage, sparse

from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError
from gloam_jax.features.pca import FeaturePCA
from gloam_jax.neighbors import KdTree

EIGEN_FEATURES = (
    "linearity",
    "planarity",
    "scattering",
    "omnivariance",
    "anisotropy",
    "eigenentropy",
    "change_of_curvature",
    "verticality",
)
POINT_FEATURES = ("density", "height", "range", "intensity")

# Ground grid: 1 m cells over +-128 m around the sensor (points beyond fall into the border
# cells), ground = lowest voxel within a 7 x 7 cell window, wide enough to reach the road
# next to a parked car or under a tree canopy.
_GROUND_CELL = 1.0
_GROUND_HALF_CELLS = 128
_GROUND_WINDOW = 7
_HEIGHT_SCALE = 5.0  # m
_MIN_HEIGHT = -5.0  # m
_RANGE_SCALE = 50.0  # m
_DENSITY_DECADES = 3.0  # log10(points / m^3) spans about -1..4
# Added to every eigenvalue (m^2, a 10 um spread): a neighbourhood of identical points
# reads as isotropic instead of dividing zero by zero.
_EIGEN_FLOOR = 1e-10


def _eigenvalues(c: np.ndarray) -> np.ndarray:
    """Closed-form eigenvalues of symmetric 3x3 matrices given as (M, 6) ``xx yy zz xy xz yz``:
    (M, 3) descending (Smith, 1961). Vectorised, where numpy's batched eigh loops per matrix."""
    xx, yy, zz, xy, xz, yz = c.T
    q = (xx + yy + zz) / 3
    p = np.sqrt(((xx - q) ** 2 + (yy - q) ** 2 + (zz - q) ** 2 + 2 * (xy**2 + xz**2 + yz**2)) / 6)
    s = np.where(p > 0, p, 1.0)  # p = 0: a multiple of I, all eigenvalues q
    bxx, byy, bzz, bxy, bxz, byz = (xx - q) / s, (yy - q) / s, (zz - q) / s, xy / s, xz / s, yz / s
    det = bxx * (byy * bzz - byz**2) - bxy * (bxy * bzz - byz * bxz) + bxz * (bxy * byz - byy * bxz)
    phi = np.arccos(np.clip(det / 2, -1.0, 1.0)) / 3
    l1 = q + 2 * p * np.cos(phi)
    l3 = q + 2 * p * np.cos(phi + 2 * np.pi / 3)
    return np.stack([l1, 3 * q - l1 - l3, l3], axis=1)


def _normal_z(c: np.ndarray, l3: np.ndarray) -> np.ndarray:
    """|z| of the unit eigenvector of the smallest eigenvalue (M,): the longest cross product
    of two rows of ``C - l3 I``. 1 where that is undefined (isotropic, or an exact line)."""
    xx, yy, zz, b, c, e = c.T
    a, d, f = xx - l3, yy - l3, zz - l3
    # Rows (a b c), (b d e), (c e f); written out, the three cross products cost a third of
    # np.cross on stacked rows.
    crosses = (
        (b * e - c * d, c * b - a * e, a * d - b * b),
        (b * f - c * e, c * c - a * f, a * e - b * c),
        (d * f - e * e, e * c - b * f, b * e - d * c),
    )
    best_z, best_n2 = np.zeros_like(a), np.zeros_like(a)
    for x, y, z in crosses:
        n2 = x * x + y * y + z * z
        longer = n2 > best_n2
        best_z, best_n2 = np.where(longer, z, best_z), np.where(longer, n2, best_n2)
    return np.where(best_n2 > 0, np.abs(best_z) / np.sqrt(np.where(best_n2 > 0, best_n2, 1.0)), 1.0)


def _eigen_features(moments: np.ndarray, k: int) -> np.ndarray:
    """Descriptors of :data:`EIGEN_FEATURES` (M, 8) from neighbourhood sums (M, 9): the first
    moments ``x y z`` and second moments ``xx yy zz xy xz yz`` over k neighbours."""
    mean = moments[:, :3] / k
    outer = mean[:, [0, 1, 2, 0, 0, 1]] * mean[:, [0, 1, 2, 1, 2, 2]]
    c = moments[:, 3:] / k - outer
    lam = np.maximum(_eigenvalues(c), 0.0) + _EIGEN_FLOOR
    e = lam / lam.sum(axis=1, keepdims=True)
    e1, e2, e3 = e.T
    return np.stack(
        [
            (e1 - e2) / e1,
            (e2 - e3) / e1,
            e3 / e1,
            3 * np.cbrt(e1 * e2 * e3),
            (e1 - e3) / e1,
            -np.sum(e * np.log(e), axis=1) / np.log(3),
            3 * e3,
            1 - _normal_z(c, lam[:, 2] - _EIGEN_FLOOR),
        ],
        axis=1,
    )


def _ground(voxels: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """Ground height (N,) under each point: the lowest voxel in a window of grid cells."""
    n = 2 * _GROUND_HALF_CELLS

    def cells(p: np.ndarray) -> np.ndarray:
        ij = np.floor(p[:, :2] / _GROUND_CELL).astype(np.int64) + _GROUND_HALF_CELLS
        ij = np.clip(ij, 0, n - 1)
        return ij[:, 0] * n + ij[:, 1]

    grid = np.full(n * n, np.inf)
    np.minimum.at(grid, cells(voxels), voxels[:, 2])
    grid = ndimage.minimum_filter(grid.reshape(n, n), size=_GROUND_WINDOW, mode="nearest")
    ground = grid.ravel()[cells(xyz)]
    # Every point's own voxel lies in its window, so this only guards cell-boundary rounding.
    return np.where(np.isfinite(ground), ground, xyz[:, 2])


class GeometricBackbone:
    """Multi-scale geometric descriptors: raw scan (N, 3+) -> features (N, D) float32.

    ``D = 8 * len(scales) + 4 - len(drop)`` (20 for the defaults); names in
    :attr:`feature_names`. Rows with non-finite coordinates get all-zero features, so the
    output stays row-aligned.
    """

    name = "geometric"

    def __init__(
        self,
        voxel_size: float = 0.25,
        scales: tuple[int, ...] | list[int] = (10, 30),
        intensity_scale: float = 1.0,
        max_height: float = 20.0,
        drop: tuple[str, ...] | list[str] = (),
        min_range: float = 0.0,
        max_range: float | None = None,
    ) -> None:
        scales = tuple(int(k) for k in scales)
        if voxel_size <= 0 or not scales or min(scales) < 3 or list(scales) != sorted(set(scales)):
            raise InputError(
                None,
                f"geometric backbone: need voxel_size > 0 and increasing scales >= 3, "
                f"got voxel_size={voxel_size}, scales={list(scales)}",
            )
        self.voxel_size = float(voxel_size)
        self.scales = scales
        self.intensity_scale = float(intensity_scale)
        self.max_height = float(max_height)
        self.drop = tuple(str(n) for n in drop)
        unknown = sorted(set(self.drop) - set(self._all_names))
        if self.max_height <= 0 or unknown or len(set(self.drop)) == len(self._all_names):
            raise InputError(
                None,
                f"geometric backbone: need max_height > 0 and drop naming some of its features "
                f"({', '.join(self._all_names)}), got max_height={max_height}, drop={list(drop)}",
            )
        self._keep = [i for i, n in enumerate(self._all_names) if n not in self.drop]
        self.min_range = float(min_range)
        self.max_range = None if max_range is None else float(max_range)
        if not 0 <= self.min_range < (np.inf if self.max_range is None else self.max_range):
            raise InputError(
                None,
                f"geometric backbone: need 0 <= min_range < max_range, got "
                f"min_range={min_range}, max_range={max_range}",
            )

    @property
    def _all_names(self) -> tuple[str, ...]:
        per_scale = tuple(f"{f}_k{k}" for k in self.scales for f in EIGEN_FEATURES)
        return per_scale + POINT_FEATURES

    @property
    def feature_names(self) -> tuple[str, ...]:
        return tuple(n for n in self._all_names if n not in self.drop)

    @property
    def dim(self) -> int:
        return len(self.feature_names)

    def fitted_intensity(self, pca: FeaturePCA) -> float | None:
        """The mean intensity (the scans' units) of the points ``pca`` was fitted on; None
        when the features read no intensity."""
        if self.intensity_scale == 0 or "intensity" in self.drop:
            return None
        return float(pca.mean[self.feature_names.index("intensity")]) / self.intensity_scale

    def options(self) -> dict[str, Any]:
        """Keyword arguments that rebuild this backbone (JSON-serialisable)."""
        return {
            "voxel_size": self.voxel_size,
            "scales": list(self.scales),
            "intensity_scale": self.intensity_scale,
            "max_height": self.max_height,
            "drop": list(self.drop),
            "min_range": self.min_range,
            "max_range": self.max_range,
        }

    def shares_grid(self, resolution: float, min_range: float, max_range: float) -> bool:
        """Whether this backbone's voxels are those of a preprocessing at ``resolution`` m
        over [``min_range``, ``max_range``] m, so :meth:`voxel_features` can run on its grid."""
        return (self.voxel_size, self.min_range, self.max_range) == (
            resolution,
            min_range,
            max_range,
        )

    def __call__(
        self,
        scan: np.ndarray,
        *,
        path: str | os.PathLike[str] | None = None,
        frame: int | None = None,
    ) -> np.ndarray:
        """Features (N, D) float32 of a raw scan (N, 3+) ``x y z [intensity]``; zeros for
        points outside [min_range, max_range] or not finite."""
        scan = pc.check_points(scan, path)
        top = np.inf if self.max_range is None else self.max_range
        try:
            band = pc.range_band(scan, self.min_range, top, path)
        except InputError:  # no valid point: all rows zero
            return np.zeros((len(scan), self.dim), np.float32)
        if len(band.xyz) == 0:
            return np.zeros((len(scan), self.dim), np.float32)
        keep, xyz, intensity = band.keep, band.xyz, band.intensity()
        grid = pc.voxel_grid(xyz, self.voxel_size)
        voxels = grid.means(xyz)
        # np.take: the same rows as per_voxel[inverse], gathered four times faster.
        features = np.concatenate(
            [
                np.take(self._per_voxel(voxels, grid.counts)[0], grid.inverse, axis=0),
                self._per_point(xyz, intensity, voxels),
            ],
            axis=1,
        )
        if self.drop:
            features = features[:, self._keep]
        if len(features) == len(scan):
            return features
        out = np.zeros((len(scan), self.dim), np.float32)
        out[keep] = features
        return out

    def voxel_features(
        self,
        xyz: np.ndarray,
        intensity: np.ndarray | None,
        grid: pc.VoxelGrid,
        centres: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The mean of :meth:`__call__`'s rows over each voxel of ``grid`` (M, D) float32,
        from the points (N, 3) float64 and intensities (N,) or None within the range and the
        voxel means ``grid.means(xyz)`` (M, 3) the caller already has: the same values
        without a second voxel grid or a row per point, where ``grid`` has this backbone's
        voxels (:meth:`shares_grid`). Also the k-NN of the voxel centres it queried (M, k)
        int32, nearest first, k its largest scale (M where fewer), for the covariances to
        reuse."""
        per_voxel, nearest = self._per_voxel(centres, grid.counts)
        features = np.concatenate(
            [per_voxel, grid.means(self._per_point(xyz, intensity, centres))], axis=1
        )
        return (features[:, self._keep] if self.drop else features), nearest

    def _per_voxel(self, voxels: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eigenvalue descriptors at every scale and the density (M, 8 * scales + 1) float32
        of voxel means (M, 3) float64 holding ``counts`` (M,) points, and their k-NN (M, k)
        int32 at the largest scale."""
        k_max = min(self.scales[-1], len(voxels))
        dist, idx = KdTree(voxels).nearest(voxels, k_max)
        # Neighbourhood sums of first and second moments as sparse (M, M) selection matrices
        # times per-voxel moments; float64 keeps ``E[xx] - E[x]^2`` exact enough at 100 m.
        moments = np.concatenate(
            [voxels, voxels[:, [0, 1, 2, 0, 0, 1]] * voxels[:, [0, 1, 2, 1, 2, 2]]], axis=1
        )
        columns = []
        for k in self.scales:
            k = min(k, k_max)
            select = sparse.csr_matrix(
                (
                    np.ones(len(voxels) * k),
                    idx[:, :k].ravel(),
                    np.arange(0, len(voxels) * k + 1, k),
                ),
                shape=(len(voxels), len(voxels)),
            )
            columns.append(_eigen_features(select @ moments, k))
        radius = np.maximum(dist[:, -1], self.voxel_size / 2)
        density = counts[idx].sum(axis=1) / (4 / 3 * np.pi * radius**3)
        columns.append(np.log10(density)[:, None] / _DENSITY_DECADES)
        return np.concatenate(columns, axis=1).astype(np.float32), idx.astype(np.int32)

    def _per_point(
        self, xyz: np.ndarray, intensity: np.ndarray | None, voxels: np.ndarray
    ) -> np.ndarray:
        """Height, range and intensity (N, 3) float32 of points (N, 3) among ``voxels``."""
        height = np.clip(xyz[:, 2] - _ground(voxels, xyz), _MIN_HEIGHT, self.max_height)
        out = np.zeros((len(xyz), 3), np.float32)
        out[:, 0] = height / _HEIGHT_SCALE
        out[:, 1] = np.linalg.norm(xyz, axis=1) / _RANGE_SCALE
        if intensity is not None:
            out[:, 2] = np.nan_to_num(
                intensity * self.intensity_scale, nan=0.0, posinf=0.0, neginf=0.0
            )
        return out
