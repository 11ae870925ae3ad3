"""Fit a model's feature region (:mod:`gloam_jax.features.novelty`) on its training scans.

The training worlds of a training config, prepared as training prepares them (the same
voxels, backbone and PCA, read from the same cache), give the PCA features the MLPs were
fitted on; the region's mean, covariance and radius come from those.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gloam_jax.features.novelty import DEFAULT_QUANTILE, fit_novelty
from gloam_jax.models import GLOAMModel
from gloam_jax.training.config import TrainConfig
from gloam_jax.training.data import open_sequences, prepare_window


def window_features(
    model: GLOAMModel,
    config: TrainConfig,
    roots: tuple[str, ...],
    sequences: tuple[str, ...],
    *,
    cache_dir: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, list[np.ndarray]]:
    """PCA features (n_i, 6) of every prepared scan of ``sequences`` under each of ``roots``,
    by ``root:sequence``, as ``config`` prepares them for training."""
    backbone = model.backbone()
    out = {}
    for seq in open_sequences(roots, sequences):
        window, _ = prepare_window(
            seq, config.preprocess, config.batch, model.pca, backbone,
            frames=config.frames, cache_dir=cache_dir, progress=progress,
        )  # fmt: skip
        out[f"{seq.root}:{seq.sequence}"] = [s.pca for s in window.scans]
    return out


def fit_model_novelty(
    model: GLOAMModel,
    config: TrainConfig,
    *,
    quantile: float = DEFAULT_QUANTILE,
    cache_dir: str | Path | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> GLOAMModel:
    """``model`` with its MLP inputs clamped to the feature region of ``config``'s training
    worlds, recorded in its provenance."""
    features = window_features(
        model, config, config.training_roots, config.sequences,
        cache_dir=cache_dir, progress=progress,
    )  # fmt: skip
    scans = [f for per_world in features.values() for f in per_world]
    novelty = fit_novelty(scans, quantile=quantile)
    record = {
        "fitted_on": {"data": list(config.training_roots), "sequences": list(config.sequences)},
        "points": int(sum(len(f) for f in scans)),
        "quantile": quantile,
    }
    provenance = {**model.provenance, "novelty": record}
    return dataclasses.replace(model, novelty=novelty, provenance=provenance)
