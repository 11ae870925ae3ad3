"""Fine-tuning the net backbone's last layer through the odometry loss (gradient mode).

The backbone is JAX too, so its weights can take the relative trajectory error's gradient.
The net's layers up to its last one (:meth:`~gloam_jax.features.net.SegNet.hidden`) run once
per scan on the host; what the training keeps is their output per net voxel and how the
prepared scan's voxel centres average it. Each step then recomputes every centre's PCA
features from the last layer's weights (:class:`~gloam_jax.learned.Head`)::

    f_centre = sum_v w_cv * pca(relu(hidden_v @ weight + bias))

with ``w_cv`` the share of the centre's raw points that lie in net voxel ``v``: exactly the
features that inference gives (the backbone's embedding per raw point, PCA-projected and
averaged per centre by :func:`gloam_jax.preprocess.preprocess_scan`), for the current weights.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from gloam_jax import io
from gloam_jax.errors import InputError
from gloam_jax.features import NetBackbone
from gloam_jax.features.net import embed, run_hidden
from gloam_jax.features.pca import FeaturePCA
from gloam_jax.geometry import real_dtype
from gloam_jax.learned import Head
from gloam_jax.preprocess import PreprocessConfig, centre_rows


class HeadData(NamedTuple):
    """What the last layer's features need, for S scans padded to Q centres: the decoder's
    input per net voxel of every scan (V, H); E (voxel, centre, weight) entries, each centre
    a row of the flattened scans (S * Q); the frozen PCA as one affine map ``w`` (D, 6),
    ``b`` (6,)."""

    hidden: Array
    voxel: Array
    centre: Array
    weight: Array
    w: Array
    b: Array


def initial_head(backbone: NetBackbone) -> Head:
    """The backbone's own last layer, as fine-tuning starts from it."""
    return Head(backbone.net.decode.weight, backbone.net.decode.bias)


def scan_entries(
    scan: np.ndarray, backbone: NetBackbone, config: PreprocessConfig, source: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One raw scan's decoder inputs per net voxel (V, H) and its (voxel, centre, weight)
    entries (E,) each: each centre's raw points counted per net voxel, over the centre's."""
    hidden, voxel = run_hidden(backbone.net, scan)
    centre = centre_rows(scan, config, source)
    kept = centre >= 0
    pairs = np.stack([centre[kept], voxel[kept]], axis=1)
    unique, counts = np.unique(pairs, axis=0, return_counts=True)
    c, v = unique[:, 0], unique[:, 1]
    per_centre = np.bincount(centre[kept], minlength=int(c.max()) + 1)
    return hidden, v, c, counts / per_centre[c]


def prepare_head(
    sequences: Sequence[io.KittiSequence],
    preprocess: PreprocessConfig,
    backbone: NetBackbone,
    pca: FeaturePCA,
    rows: int,
    *,
    frames: int | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> HeadData:
    """:class:`HeadData` of the first ``frames`` scans of each sequence (as
    :func:`gloam_jax.training.data.open_sequences` lists them for
    :func:`~gloam_jax.training.data.load_windows`), their centres padded to ``rows`` (Q)."""
    hidden, voxel, centre, weight = [], [], [], []
    offset, s = 0, 0
    for seq in sequences:
        n = len(seq) if frames is None else min(frames, len(seq))
        for i in range(n):
            source = str(seq.scan_path(i))
            h, v, c, w = scan_entries(seq.scan(i), backbone, preprocess, source)
            if len(c) and c.max() >= rows:
                raise InputError(source, f"{c.max() + 1} voxel centres, the batch holds {rows}")
            hidden.append(h), voxel.append(v + offset), centre.append(c + s * rows)
            weight.append(w)
            offset, s = offset + len(h), s + 1
            if progress is not None:
                progress(f"backbone {seq.sequence}", i + 1, n)
    real = real_dtype()
    W, b = pca.affine()
    return HeadData(
        hidden=jnp.asarray(np.concatenate(hidden), real),
        voxel=jnp.asarray(np.concatenate(voxel), jnp.int32),
        centre=jnp.asarray(np.concatenate(centre), jnp.int32),
        weight=jnp.asarray(np.concatenate(weight), real),
        w=jnp.asarray(W, real),
        b=jnp.asarray(b, real),
    )


def head_features(head: Head, data: HeadData, shape: tuple[int, int]) -> Array:
    """The scans' PCA features (S, Q, 6) under the last layer ``head``; padded centres 0."""
    # PCA per net voxel (V, 6), before the mean: it is affine, so it commutes with the mean.
    f = embed(head.weight, head.bias, data.hidden) @ data.w + data.b
    S, Q = shape
    out = jax.ops.segment_sum(data.weight[:, None] * f[data.voxel], data.centre, num_segments=S * Q)
    return out.reshape(S, Q, -1)
