"""Net backbone: a small RandLA-Net-style point segmentation network in JAX (equinox).

Equinox, not flax: it is already installed (optimistix depends on it), and its models are
plain pytrees, so the weights pass through ``jax.grad``, ``optax`` and the odometry's own
jitted functions like any other array tree (fine-tuning through GICP needs nothing more).

One scan, on the host (NumPy and scipy's k-d tree), then one jitted call:

1. voxel means at ``voxel_size`` (level 0, M points) and their k-NN graph (M, K); on a
   registration's grid (:class:`NetBackbone`'s ``grid``), that grid's voxel means in its range
   band and their ``k`` nearest, which the covariances then share;
2. random sampling of one voxel in ``ratio`` (level 1; a fixed seed over the voxels in
   sorted key order, so the choice does not depend on the order of the scan's points), the
   level-1 k-NN graph and each voxel's nearest level-1 point;
3. both levels padded to size buckets (padded rows only ever read themselves, so no mask is
   needed inside the network);
4. the network: per-voxel inputs (range / 50 m, z / 3 m and, unless ``intensity`` is off,
   intensity) -> dense; local aggregation (local spatial encoding of relative positions +
   attentive pooling) at level 0; max-pooling onto level 1 over each sampled voxel's level-0
   neighbours; local aggregation at level 1; nearest-neighbour upsampling, concatenated with
   the level-0 features -> dense + ReLU: the embedding (M, ``embed``); -> dense: class logits.

Each raw point gets its voxel's embedding, so the features are row-aligned with the scan.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import rankdata

from gloam_jax import pointcloud as pc
from gloam_jax.errors import InputError
from gloam_jax.io.files import write_npz
from gloam_jax.neighbors import KdTree

# Training classes: SemanticKITTI ids; moving objects fold into their static class (one scan
# cannot tell motion).
CLASSES = (
    "car", "bicycle", "person", "bicyclist", "road", "sidewalk", "building", "fence",
    "other-structure", "vegetation", "trunk", "terrain", "pole", "traffic-sign",
)  # fmt: skip
_KITTI_IDS = (10, 11, 30, 31, 40, 48, 50, 51, 52, 70, 71, 72, 80, 81)
_MOVING = {252: 10, 253: 31, 254: 30}
_LABEL_LUT = np.full(260, -1, np.int32)
_LABEL_LUT[list(_KITTI_IDS)] = np.arange(len(_KITTI_IDS))
_LABEL_LUT[list(_MOVING)] = [_KITTI_IDS.index(v) for v in _MOVING.values()]

NET_FORMAT = "gloam-jax-net"
# The shipped networks by name (gloam_jax/data/): "default" reads intensity, "no-intensity"
# is geometry only, "intensity-rank" reads each voxel's intensity rank in its scan
# (experiments/net_intensity).
SHIPPED_NETS = {
    name: Path(__file__).resolve().parent.parent / "data" / file
    for name, file in (
        ("default", "net_default.npz"),
        ("no-intensity", "net_no_intensity.npz"),
        ("intensity-rank", "net_intensity_rank.npz"),
    )
}
_RANGE_SCALE = 50.0  # m
_HEIGHT_SCALE = 3.0  # m


def class_index(labels: np.ndarray) -> np.ndarray:
    """Training class (N,) int32 of SemanticKITTI ids (N,); -1 for unlabeled and unknown."""
    labels = np.asarray(labels).astype(np.int64) & 0xFFFF
    return np.where(labels < len(_LABEL_LUT), _LABEL_LUT[np.minimum(labels, 259)], -1)


@dataclasses.dataclass(frozen=True)
class NetConfig:
    """Hyperparameters that set the network's shapes and its host-side graph."""

    voxel_size: float = 0.3  # m
    k: int = 16  # neighbours per point, both levels
    ratio: int = 4  # level-0 voxels per level-1 point
    widths: tuple[int, int, int] = (8, 32, 64)  # stem, level 0, level 1
    embed: int = 32
    num_classes: int = len(CLASSES)
    # Feed each voxel's mean intensity. Off: geometry only (range, height, neighbourhoods), for
    # data whose intensity scale or model differs from the training scans' (other sensors, real
    # scans, other simulators): experiments/net_intensity.
    intensity: bool = True
    # Feed each voxel's mean intensity as its rank among the scan's voxels (0..1) instead:
    # blind to units, gain and offset (other monotone responses nearly: the ranks are of voxel
    # means), though not to another order of materials.
    intensity_rank: bool = False


class NetInputs(NamedTuple):
    """One padded scan: xyz (N0, 3), inputs (N0, 3), nbr0 (N0, K), sub (N1,), nbr1 (N1, K)
    and up (N0,); indices int32 into level 0 (nbr0, sub) or level 1 (nbr1, up)."""

    xyz: np.ndarray | jax.Array
    inputs: np.ndarray | jax.Array
    nbr0: np.ndarray | jax.Array
    sub: np.ndarray | jax.Array
    nbr1: np.ndarray | jax.Array
    up: np.ndarray | jax.Array


class Dense(eqx.Module):
    """``x @ weight + bias`` over any leading axes: (..., n_in) -> (..., n_out)."""

    weight: jax.Array
    bias: jax.Array

    def __init__(self, n_in: int, n_out: int, *, key: jax.Array) -> None:
        # He initialisation: every Dense but the classifier feeds a ReLU.
        self.weight = jax.random.normal(key, (n_in, n_out)) * np.sqrt(2.0 / n_in)
        self.bias = jnp.zeros(n_out)

    def __call__(self, x: jax.Array) -> jax.Array:
        return x @ self.weight + self.bias


class LocalAggregation(eqx.Module):
    """Local spatial encoding + attentive pooling (RandLA-Net): features (N, c_in) at points
    xyz (N, 3) with neighbours (N, K) -> (N, c_out). ``chunked``: on the CPU, rows a few at a
    time (one scan's inference); off, all at once (training's vmapped, differentiated
    batches, which chunks made slower)."""

    position: Dense
    feature: Dense
    score: Dense
    out: Dense

    def __init__(self, c_in: int, c_out: int, *, key: jax.Array) -> None:
        k1, k2, k3, k4 = jax.random.split(key, 4)
        half = c_out // 2
        self.position = Dense(4, half, key=k1)
        self.feature = Dense(c_in, c_out - half, key=k2)
        self.score = Dense(c_out, c_out, key=k3)
        self.out = Dense(c_out, c_out, key=k4)

    def __call__(
        self, h: jax.Array, xyz: jax.Array, nbr: jax.Array, chunked: bool = True
    ) -> jax.Array:
        half = self.position.weight.shape[1]
        xyz, nbr = jnp.asarray(xyz), jnp.asarray(nbr)  # indexed by traced rows below
        # Transform before gathering: N rows instead of N * K. The attention score of the
        # concatenation [enc, f] splits likewise: its f half is a per-point product, gathered.
        f = jax.nn.relu(self.feature(h))
        f_score = f @ self.score.weight[half:] + self.score.bias

        def rows(i: jax.Array) -> jax.Array:
            nb = nbr[i]  # (c, K)
            rel = xyz[nb] - xyz[i][:, None, :]  # (c, K, 3)
            dist = jnp.sqrt(jnp.sum(rel * rel, axis=-1, keepdims=True))
            enc = jax.nn.relu(self.position(jnp.concatenate([rel, dist], axis=-1)))
            score = enc @ self.score.weight[:half] + f_score[nb]  # (c, K, c_out)
            attention = jax.nn.softmax(score, axis=1)  # per channel, over neighbours
            pooled = jnp.concatenate(
                [jnp.sum(attention[..., :half] * enc, axis=1),
                 jnp.sum(attention[..., half:] * f[nb], axis=1)], axis=-1,
            )  # fmt: skip
            return jax.nn.relu(self.out(pooled))

        if not chunked or jax.default_backend() != "cpu":  # an accelerator: all in one pass
            return rows(jnp.arange(nbr.shape[0], dtype=jnp.int32))
        edge_bytes = nbr.shape[1] * self.out.weight.shape[1] * 4
        return in_chunks(rows, nbr.shape[0], max(1, _CHUNK_BYTES // edge_bytes))


# On the CPU the per-edge tensors (rows x K x channels) are evaluated this many bytes at a
# time, so they stay in a core's L2 cache: whole, they were written to and read from memory
# several times, and that, not the arithmetic, set the network's time (experiments/net_chunks).
_CHUNK_BYTES = 2 << 20


def in_chunks(fn: Callable[[jax.Array], jax.Array], n: int, chunk: int) -> jax.Array:
    """``fn`` of row indices (c,) -> (c, d), over rows 0..n-1 in chunks of ``chunk``
    (``lax.map``; the last chunk repeats row n-1 to fill it): (n, d)."""
    chunk = min(chunk, n)
    m = -(-n // chunk) * chunk
    index = jnp.minimum(jnp.arange(m, dtype=jnp.int32), n - 1).reshape(-1, chunk)
    out = jax.lax.map(fn, index)
    return out.reshape(m, out.shape[-1])[:n]


class SegNet(eqx.Module):
    """The network: :class:`NetInputs` of one scan -> embedding (N0, embed), logits (N0, C)."""

    stem: Dense
    local0: LocalAggregation
    local1: LocalAggregation
    decode: Dense
    classify: Dense
    config: NetConfig = eqx.field(static=True)

    def __init__(self, config: NetConfig = NetConfig(), *, key: jax.Array) -> None:
        k = jax.random.split(key, 5)
        w0, w1, w2 = config.widths
        self.config = config
        self.stem = Dense(3 if config.intensity else 2, w0, key=k[0])
        self.local0 = LocalAggregation(w0, w1, key=k[1])
        self.local1 = LocalAggregation(w1, w2, key=k[2])
        self.decode = Dense(w1 + w2, config.embed, key=k[3])
        self.classify = Dense(config.embed, config.num_classes, key=k[4])

    def __call__(self, x: NetInputs, chunked: bool = True) -> tuple[jax.Array, jax.Array]:
        embedding = self.embedding(x, chunked)
        return embedding, self.classify(embedding)

    def embedding(self, x: NetInputs, chunked: bool = True) -> jax.Array:
        """The embedding (N0, embed) alone, without the classifier."""
        return embed(self.decode.weight, self.decode.bias, self.hidden(x, chunked))

    def hidden(self, x: NetInputs, chunked: bool = True) -> jax.Array:
        """The decoder's input (N0, widths[1] + widths[2]): all but the last layers
        (``chunked``: see :class:`LocalAggregation`)."""
        h0 = self.local0(jax.nn.relu(self.stem(x.inputs)), x.xyz, x.nbr0, chunked)
        h1 = jnp.max(h0[x.nbr0[x.sub]], axis=1)  # each sampled voxel pools its neighbourhood
        h1 = self.local1(h1, x.xyz[x.sub], x.nbr1, chunked)
        return jnp.concatenate([h0, h1[x.up]], axis=-1)


def embed(weight: jax.Array, bias: jax.Array, hidden: jax.Array) -> jax.Array:
    """The embedding (..., embed) of the decoder's input (..., widths[1] + widths[2]) by the
    last layer ``weight``, ``bias``: the one fine-tuning through the odometry loss trains."""
    return jax.nn.relu(hidden @ weight + bias)


def with_decode(net: SegNet, weight: jax.Array, bias: jax.Array) -> SegNet:
    """``net`` with the last layer's weights replaced (a fine-tuned one)."""
    if weight.shape != net.decode.weight.shape or bias.shape != net.decode.bias.shape:
        raise InputError(
            None,
            f"a decode layer of shapes {weight.shape}, {bias.shape} does not fit the network's "
            f"{net.decode.weight.shape}, {net.decode.bias.shape}",
        )
    return eqx.tree_at(lambda n: (n.decode.weight, n.decode.bias), net, (weight, bias))


def voxelize(scan: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel means of a finite scan (N, 3+): xyz (M, 3) float64, intensity (M,) (0 without
    a fourth column) and each point's voxel (N,)."""
    xyz = np.asarray(scan[:, :3], np.float64)
    inverse, counts = pc.voxel_index(xyz, voxel_size)
    cols = [xyz[:, i] for i in range(3)]
    if scan.shape[1] > 3:
        cols.append(np.nan_to_num(np.asarray(scan[:, 3], np.float64), posinf=0.0, neginf=0.0))
    sums = np.stack([np.bincount(inverse, weights=c, minlength=len(counts)) for c in cols], 1)
    means = sums / counts[:, None]
    intensity = means[:, 3] if scan.shape[1] > 3 else np.zeros(len(counts))
    return means[:, :3], intensity, inverse


def _knn(tree: KdTree, queries: np.ndarray, k: int) -> np.ndarray:
    """Indices (Q, k) of the k nearest tree points; short clouds repeat the nearest."""
    k_eff = min(k, len(tree))
    idx = tree.nearest(queries, k_eff)[1]
    if k_eff < k:
        idx = np.concatenate([idx, np.repeat(idx[:, :1], k - k_eff, axis=1)], axis=1)
    return idx.astype(np.int32)


def sample_level1(m: int, ratio: int) -> np.ndarray:
    """Level-1 voxels (ceil(m / ratio),) sorted: a fixed-seed random sample of m voxels."""
    n1 = -(-m // ratio)
    return np.sort(np.random.default_rng(0).choice(m, n1, replace=False)).astype(np.int32)


def nearest_sampled(
    nbr0: np.ndarray, sub: np.ndarray, tree1: KdTree, xyz: np.ndarray
) -> np.ndarray:
    """Each voxel's nearest level-1 point (M,) int32, an index into ``sub`` (the sampled
    voxels, sorted; ``tree1`` holds their points): the first sampled voxel in its k-NN row
    ``nbr0`` (M, K), nearest first, is the nearest of them all; only rows without one query
    the tree (with ratio 4 and K = 10, about one row in twenty)."""
    level1 = np.full(len(xyz), -1, np.int32)
    level1[sub] = np.arange(len(sub), dtype=np.int32)
    candidates = level1[nbr0]  # (M, K): -1 where not sampled
    first = np.argmax(candidates >= 0, axis=1)
    up = candidates[np.arange(len(xyz)), first]
    missing = np.flatnonzero(up < 0)
    if len(missing):
        up[missing] = _knn(tree1, xyz[missing], 1)[:, 0]
    return up


def build_inputs(
    xyz: np.ndarray,
    intensity: np.ndarray,
    config: NetConfig,
    size: int | None = None,
    nbr0: np.ndarray | None = None,
) -> NetInputs:
    """The network's inputs for M >= 1 voxels xyz (M, 3), intensity (M,), level 0 padded to
    ``size`` rows (default: M's bucket) and level 1 to ``ceil(size / ratio)``; ``nbr0``: the
    level-0 k-NN (M, K) where already found (else ``config.k`` of them are queried)."""
    m = len(xyz)
    size = pc.bucket_size(m) if size is None else size
    sub = sample_level1(m, config.ratio)
    nbr0 = _knn(KdTree(xyz), xyz, config.k) if nbr0 is None else nbr0
    tree1 = KdTree(xyz[sub])
    nbr1 = _knn(tree1, xyz[sub], config.k)
    up = nearest_sampled(nbr0, sub, tree1, xyz)
    columns = [np.linalg.norm(xyz, axis=1) / _RANGE_SCALE, xyz[:, 2] / _HEIGHT_SCALE]
    features = np.stack(columns + [intensity] if config.intensity else columns, 1)
    n1 = -(-size // config.ratio)
    # Padded rows point at themselves, so real rows never read them.
    pad0 = np.arange(m, size, dtype=np.int32)
    pad1 = np.arange(len(sub), n1, dtype=np.int32)
    return NetInputs(
        xyz=pc.pad(xyz.astype(np.float32), size)[0],
        inputs=pc.pad(features.astype(np.float32), size)[0],
        nbr0=np.concatenate([nbr0, np.repeat(pad0[:, None], nbr0.shape[1], 1)]),
        sub=np.concatenate([sub, np.zeros(len(pad1), np.int32)]),
        nbr1=np.concatenate([nbr1, np.repeat(pad1[:, None], config.k, 1)]),
        up=np.concatenate([up, np.zeros(len(pad0), np.int32)]),
    )


@eqx.filter_jit
def _forward(net: SegNet, x: NetInputs) -> tuple[jax.Array, jax.Array]:
    return net(x)


@eqx.filter_jit
def _embedding(net: SegNet, x: NetInputs) -> jax.Array:
    return net.embedding(x)


@eqx.filter_jit
def _hidden(net: SegNet, x: NetInputs) -> jax.Array:
    return net.hidden(x)


def scan_intensity(intensity: np.ndarray, config: NetConfig) -> np.ndarray:
    """What the network reads of one scan's voxel intensities (M,): as measured, or each one's
    rank in the scan (ties share their mean rank), scaled to (0, 1)."""
    if not config.intensity_rank or len(intensity) == 0:
        return intensity
    return (rankdata(intensity, method="average") - 0.5) / len(intensity)


def _scan_voxels(scan: np.ndarray, config: NetConfig) -> tuple[NetInputs, np.ndarray, int] | None:
    """The network's inputs for a raw scan (N, 3+), each row's voxel (N,) (-1 for rows with
    non-finite coordinates) and the voxel count; None for a scan without finite rows."""
    finite = np.all(np.isfinite(scan[:, :3]), axis=1)
    if not finite.any():
        return None
    xyz, intensity, inverse = voxelize(scan[finite], config.voxel_size)
    voxel = np.full(len(scan), -1, np.int64)
    voxel[finite] = inverse
    return build_inputs(xyz, scan_intensity(intensity, config), config), voxel, len(xyz)


def _rows(values: jax.Array, m: int, voxel: np.ndarray) -> np.ndarray:
    """Per-voxel ``values`` (>= m, d) -> float32 per raw row (N,) of ``voxel`` (-1: zeros)."""
    values = np.asarray(values)[:m]
    if voxel.min() >= 0:  # every row finite: one gather, np.take being the fast one
        return np.take(values, voxel, axis=0)
    out = np.zeros((len(voxel), values.shape[1]), np.float32)
    finite = voxel >= 0
    out[finite] = np.take(values, voxel[finite], axis=0)
    return out


def run_scan(net: SegNet, scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Embedding (N, embed) float32 and logits (N, C) of a raw scan (N, 3+), row-aligned;
    rows with non-finite coordinates get zeros."""
    c = net.config
    voxels = _scan_voxels(scan, c)
    if voxels is None:
        return (np.zeros((len(scan), c.embed), np.float32),
                np.zeros((len(scan), c.num_classes), np.float32))  # fmt: skip
    inputs, voxel, m = voxels
    e, lg = _forward(net, inputs)
    return _rows(e, m, voxel), _rows(lg, m, voxel)


def run_embedding(net: SegNet, scan: np.ndarray) -> np.ndarray:
    """:func:`run_scan`'s embedding alone (N, embed), without evaluating the classifier."""
    voxels = _scan_voxels(scan, net.config)
    if voxels is None:
        return np.zeros((len(scan), net.config.embed), np.float32)
    inputs, voxel, m = voxels
    return _rows(_embedding(net, inputs), m, voxel)


def run_hidden(net: SegNet, scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The decoder's input per voxel (M, widths[1] + widths[2]) float32 and each raw row's
    voxel (N,) (-1: non-finite): :func:`embed` of it with ``net.decode``'s weights, indexed by
    the voxels, is :func:`run_scan`'s embedding. Fine-tuning the last layer needs only these."""
    voxels = _scan_voxels(scan, net.config)
    if voxels is None:
        return np.zeros((0, sum(net.config.widths[1:])), np.float32), np.full(len(scan), -1)
    inputs, voxel, m = voxels
    return np.asarray(_hidden(net, inputs))[:m], voxel


def _named_leaves(net: SegNet) -> dict[str, np.ndarray]:
    leaves = jax.tree_util.tree_flatten_with_path(eqx.filter(net, eqx.is_array))[0]
    return {jax.tree_util.keystr(path): np.asarray(v) for path, v in leaves}


def save_net(path: str | os.PathLike[str], net: SegNet, provenance: dict[str, Any]) -> None:
    """Write the weights, the :class:`NetConfig` and ``provenance`` as one ``.npz``, atomically."""
    metadata = {
        "format": NET_FORMAT,
        "config": dataclasses.asdict(net.config),
        "provenance": provenance,
    }
    arrays = {f"w{i}": v for i, v in enumerate(_named_leaves(net).values())}
    write_npz(path, metadata=np.array(json.dumps(metadata)), **arrays)


def load_net(path: str | os.PathLike[str]) -> tuple[SegNet, dict[str, Any]]:
    """The network and its provenance from a file written by :func:`save_net`."""
    try:
        with np.load(path, allow_pickle=False) as f:
            metadata = json.loads(str(f["metadata"]))
            arrays = {k: f[k] for k in f.files if k != "metadata"}
    except (OSError, ValueError, KeyError, EOFError) as e:
        raise InputError(path, f"cannot read network weights ({e})") from None
    if metadata.get("format") != NET_FORMAT:
        raise InputError(path, f"not a {NET_FORMAT} file")
    try:
        cfg = metadata["config"]
        config = NetConfig(**{**cfg, "widths": tuple(cfg["widths"])})
    except (KeyError, TypeError) as e:
        raise InputError(path, f"bad network config ({e})") from None
    skeleton = SegNet(config, key=jax.random.key(0))
    params, static = eqx.partition(skeleton, eqx.is_array)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    if len(arrays) != len(leaves):
        raise InputError(path, f"has {len(arrays)} weight arrays, the network needs {len(leaves)}")
    loaded = [arrays[f"w{i}"] for i in range(len(leaves))]
    for i, (a, b) in enumerate(zip(loaded, leaves, strict=True)):
        if a.shape != b.shape:
            raise InputError(path, f"weight w{i} has shape {a.shape}, expected {b.shape}")
    params = jax.tree_util.tree_unflatten(treedef, [jnp.asarray(a, jnp.float32) for a in loaded])
    return eqx.combine(params, static), metadata.get("provenance", {})


def _grid_setting(grid: dict[str, float]) -> dict[str, float]:
    """A checked ``grid`` option of :class:`NetBackbone`."""
    keys = {"resolution", "min_range", "max_range", "k"}
    if not isinstance(grid, dict) or set(grid) != keys:
        raise InputError(
            None, f"the net backbone's grid needs exactly {sorted(keys)}, not {grid!r}"
        )
    ok = grid["resolution"] > 0 and 0 <= grid["min_range"] < grid["max_range"]
    if not ok or grid["k"] != int(grid["k"]) or grid["k"] < 1:
        raise InputError(None, f"bad net backbone grid {grid!r}")
    return {k: float(v) for k, v in grid.items() if k != "k"} | {"k": int(grid["k"])}


class NetBackbone:
    """Per-point embeddings of a trained :class:`SegNet`: raw scan (N, 3+) -> (N, embed).

    ``weights``: a file from ``gloam train-backbone``, or the name of a shipped network:
    ``"default"`` (``gloam_jax/data/net_default.npz``), ``"no-intensity"`` (geometry only) or
    ``"intensity-rank"`` (intensity as its rank in the scan).

    ``grid``: None, the network's own voxels (``voxel_size``) and k-NN (``k``) over the whole
    scan; or ``{"resolution", "min_range", "max_range", "k"}``: the voxel means of a
    registration's preprocessing at that resolution and range band, with their ``k`` nearest
    at level 0, which the covariances then share (:meth:`voxel_features`;
    experiments/net_grid). Each raw point gets its voxel's embedding.
    """

    name = "net"

    def __init__(
        self, weights: str | os.PathLike[str] = "default", grid: dict[str, float] | None = None
    ) -> None:
        self.weights = str(weights)
        self.net, self.provenance = load_net(SHIPPED_NETS.get(self.weights, weights))
        self.grid = None if grid is None else _grid_setting(grid)

    @property
    def dim(self) -> int:
        return self.net.config.embed

    @property
    def reads_intensity_order(self) -> bool:
        """Whether the network reads each voxel's intensity rank in its scan (no units)."""
        return self.net.config.intensity and self.net.config.intensity_rank

    def fitted_intensity(self, pca: object = None) -> float | None:
        """The mean intensity of the network's training points (its weight file's
        provenance); None when it reads no intensity or the file does not say."""
        reads_units = self.net.config.intensity and not self.reads_intensity_order
        return self.provenance.get("intensity_mean") if reads_units else None

    def options(self) -> dict[str, Any]:
        """Keyword arguments that rebuild this backbone (JSON-serialisable)."""
        return {"weights": self.weights} | ({} if self.grid is None else {"grid": self.grid})

    def shares_grid(self, resolution: float, min_range: float, max_range: float) -> bool:
        """Whether this backbone runs on the voxels of a preprocessing at ``resolution`` m over
        [``min_range``, ``max_range``] m, so :meth:`voxel_features` can run on its grid."""
        g = self.grid
        return g is not None and (g["resolution"], g["min_range"], g["max_range"]) == (
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
        """Features (N, embed) float32 of a raw scan (N, 3+) ``x y z [intensity]``; on a
        ``grid``, zeros for points outside its range band or not finite."""
        scan = pc.check_points(scan, path)
        if self.grid is None:
            return run_embedding(self.net, scan)
        out = np.zeros((len(scan), self.dim), np.float32)
        try:
            band = pc.range_band(scan, self.grid["min_range"], self.grid["max_range"], path)
        except InputError:  # no valid point: all rows zero
            return out
        if len(band.xyz) == 0:
            return out
        grid = pc.voxel_grid(band.xyz, self.grid["resolution"])
        embedding = self.voxel_features(band.xyz, band.intensity(), grid, grid.means(band.xyz))[0]
        out[band.keep] = np.take(embedding, grid.inverse, axis=0)
        return out

    def voxel_features(
        self,
        xyz: np.ndarray,
        intensity: np.ndarray | None,
        grid: pc.VoxelGrid,
        centres: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The embedding (M, embed) float32 of each voxel of ``grid`` (this backbone's
        ``grid``, :meth:`shares_grid`), from the points (N, 3) float64 and intensities (N,) or
        None within the range band and their voxel means ``grid.means(xyz)`` (M, 3), and the
        k-NN of those means it queried (M, k) int32, nearest first (M columns where fewer),
        for the covariances to reuse."""
        values = np.zeros(len(centres))
        if intensity is not None:
            finite = np.nan_to_num(np.asarray(intensity, np.float64), posinf=0.0, neginf=0.0)
            values = grid.means(finite[:, None])[:, 0]
        nbr0 = _knn(KdTree(centres), centres, self.grid["k"])  # a short cloud repeats columns
        inputs = build_inputs(centres, scan_intensity(values, self.net.config), self.net.config,
                              nbr0=nbr0)  # fmt: skip
        embedding = np.asarray(_embedding(self.net, inputs))[: len(centres)]
        return embedding, nbr0[:, : min(self.grid["k"], len(centres))]

    def segment(self, scan: np.ndarray, path: str | os.PathLike[str] | None = None) -> np.ndarray:
        """SemanticKITTI class ids (N,) uint16 of a raw scan (N, 3+): the network's most likely
        class per point; 0 (unlabeled) where a coordinate is not finite."""
        scan = pc.check_points(scan, path)
        logits = run_scan(self.net, scan)[1]
        ids = np.asarray(_KITTI_IDS, np.uint16)[np.argmax(logits, axis=1)]
        return np.where(np.isfinite(scan[:, :3]).all(axis=1), ids, np.uint16(0))
