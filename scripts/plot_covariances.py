"""Covariance shapes of one scan as ellipsoids: raw k-NN vs plane vs learned (Fig. 4 of the paper).

    python scripts/plot_covariances.py SCAN --model model.npz --center 10 12 --out cov.png

SCAN is any scan ``gloam_jax.io.read_scan`` reads. The scan is voxel-downsampled and gets k-NN
covariances as in odometry; the learned panel runs Algorithm 1 with the model's backbone, PCA
and Eigenvalue Estimation MLP. Without ``--model`` it uses a randomly initialised model (PCA
fitted on this scan), labelled as such. Each ellipsoid is scaled so that its longest
semi-axis has the same length: the panels compare shapes, not sizes (the three
regularisers live on different scales). Colour: red = line, green = plane, blue = sphere.

docs/img/covariances.png is frame 0 of test world 301 (``scripts/simulate_protocol.py --split
test``, simulation seed 0: ``data/protocol2/sequences/301/velodyne/000000.bin``) with the shipped
model (``--model gloam_jax/data/gloam_default.npz``) and the other defaults.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from gloam_jax import covariance as cov  # noqa: E402
from gloam_jax import io  # noqa: E402
from gloam_jax import pointcloud as pc  # noqa: E402
from gloam_jax.features import fit_pca, get_backbone  # noqa: E402
from gloam_jax.models import init_model, load_model  # noqa: E402
from gloam_jax.neighbors import KdTree  # noqa: E402


def unit_sphere(n_lon: int = 10, n_lat: int = 6) -> np.ndarray:
    """Quad faces of a UV sphere: (F, 4, 3)."""
    lon = np.linspace(0, 2 * np.pi, n_lon + 1)
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    lo, la = np.meshgrid(lon, lat, indexing="ij")
    v = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)
    return np.stack([v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]], axis=2).reshape(-1, 4, 3)


def shape_colours(values: np.ndarray) -> np.ndarray:
    """RGB (N, 3) = (linearity, planarity, scattering) of ascending eigenvalues (N, 3)."""
    l3, l2, l1 = np.maximum(values, 0).T
    l1 = np.maximum(l1, 1e-30)
    return np.stack([(l1 - l2) / l1, (l2 - l3) / l1, l3 / l1], axis=1)


def ellipsoid_faces(centres, covariances, size, sphere, light):
    """Faces (N * F, 4, 3) and shaded colours (N * F, 3) of ellipsoids whose longest
    semi-axis is ``size``."""
    values, vectors = np.linalg.eigh(covariances)
    values = np.maximum(values, 0)
    axes = size * np.sqrt(values / np.maximum(values[:, 2:], 1e-30))  # (N, 3)
    shape = vectors * axes[:, None, :]  # columns scaled by semi-axes
    faces = np.einsum("nij,fkj->nfki", shape, sphere) + centres[:, None, None, :]
    # Lambert shading with the unit-sphere normals mapped through the inverse shape.
    normals = np.einsum("nij,fj->nfi", vectors / np.maximum(axes[:, None, :], 1e-9), sphere.mean(1))
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    shade = 0.35 + 0.65 * np.abs(normals @ light)
    colours = shape_colours(values)[:, None, :] * shade[..., None]
    return faces.reshape(-1, 4, 3), np.clip(colours.reshape(-1, 3), 0, 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("scan", type=Path, help="scan file (.bin, .pcd, .ply, .npy)")
    parser.add_argument("--model", type=Path, help="model .npz (default: random init)")
    parser.add_argument("--center", type=float, nargs=2, default=(10.0, 12.0), metavar=("X", "Y"))
    parser.add_argument("--size", type=float, default=20.0, help="crop side (m)")
    parser.add_argument("--voxel", type=float, default=0.5, help="downsampling (m), as odometry")
    parser.add_argument("--neighbors", type=int, default=10, help="k of the k-NN covariances")
    parser.add_argument("--seed", type=int, default=0, help="random model seed")
    parser.add_argument("--elev", type=float, default=35.0, help="view elevation (deg)")
    parser.add_argument("--azim", type=float, default=-120.0, help="view azimuth (deg)")
    parser.add_argument("--out", type=Path, default=Path("covariances.png"))
    args = parser.parse_args()

    scan, _ = pc.drop_invalid(io.read_scan(args.scan), str(args.scan))
    if args.model is not None:
        model = load_model(args.model)
        label = f"learned ({args.model.name})"
    else:
        model = None
        label = f"learned (random init, seed {args.seed})"
    backbone = model.backbone() if model else get_backbone()
    raw_features = backbone(scan, path=args.scan)
    if model is None:
        model = init_model(jax.random.PRNGKey(args.seed), fit_pca(raw_features))

    # Features averaged per voxel along with the coordinates, as the registration sees them.
    cloud = pc.voxel_downsample(
        np.concatenate([scan[:, :3], raw_features], axis=1).astype(np.float64), args.voxel
    )
    points, features = cloud[:, :3], cloud[:, 3:]
    neighbours, _ = KdTree(points).query(points, args.neighbors)
    half = args.size / 2
    crop = np.all(np.abs(points[:, :2] - np.asarray(args.center)) <= half, axis=1)
    if not crop.any():
        raise SystemExit(f"no points within {half} m of {tuple(args.center)}")
    raw = cov.knn_covariances(jnp.asarray(points), jnp.asarray(neighbours[crop]))
    eigenvalues = model.eigenvalue(model.pca_features(jnp.asarray(features[crop], jnp.float32)))
    panels = {
        "raw k-NN covariance": raw,
        "plane (eps, 1, 1) (GICP)": cov.plane(raw),
        label: cov.learned(raw, eigenvalues, model.eps, model.max_thickness),
    }

    sphere = unit_sphere()
    light = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    size = 0.45 * args.voxel
    centres = points[crop]
    fig = plt.figure(figsize=(18, 6))
    for i, (title, covariances) in enumerate(panels.items()):
        ax = fig.add_subplot(1, 3, i + 1, projection="3d")
        faces, colours = ellipsoid_faces(
            centres, np.asarray(covariances, np.float64), size, sphere, light
        )
        ax.add_collection3d(Poly3DCollection(faces, facecolors=colours, linewidths=0))
        lo, hi = centres.min(0), centres.max(0)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]))
        ax.set_box_aspect(hi - lo, zoom=1.25)
        ax.view_init(elev=args.elev, azim=args.azim)
        ax.set_title(title, fontsize=13)
        ax.set_axis_off()
    fig.suptitle(
        f"{args.scan.name}: {crop.sum()} voxels ({args.voxel} m) in {args.size:g} x "
        f"{args.size:g} m around {tuple(args.center)}; k = {args.neighbors}; each ellipsoid "
        f"scaled to a longest semi-axis of {size:.2f} m; red line, green plane, blue sphere",
        fontsize=11,
    )
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.9, wspace=0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
