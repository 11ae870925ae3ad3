"""Per-point features from a backbone, and their frozen PCA to six dimensions.

A backbone maps one raw scan (N, 3+) ``x y z [intensity]`` (plus, optionally, the scan's
path or frame index, which file-based backbones need) to features (N, D) float32,
row-aligned with the scan's points::

    backbone = get_backbone("geometric")        # or "net", or "precomputed" with folder=...
    raw = backbone(scan, path=seq.scan_path(i))  # (N, D)
    f = pca.transform(raw)                       # (N, 6), pca = fit_pca([...]) once

``backbone.name`` and ``backbone.options()`` rebuild it: ``get_backbone(name, **options)``.
"""

from __future__ import annotations

import os
from typing import Any, Protocol

import numpy as np

from gloam_jax.errors import InputError
from gloam_jax.features.geometric import GeometricBackbone
from gloam_jax.features.net import NetBackbone
from gloam_jax.features.pca import FeaturePCA, fit_pca
from gloam_jax.features.precomputed import PrecomputedBackbone

__all__ = [
    "BACKBONES",
    "Backbone",
    "FeaturePCA",
    "GeometricBackbone",
    "NetBackbone",
    "PrecomputedBackbone",
    "fit_pca",
    "get_backbone",
]


class Backbone(Protocol):
    """Raw scan -> per-point features."""

    name: str

    def options(self) -> dict[str, Any]: ...

    def __call__(
        self,
        scan: np.ndarray,
        *,
        path: str | os.PathLike[str] | None = None,
        frame: int | None = None,
    ) -> np.ndarray: ...


BACKBONES: dict[str, type] = {
    GeometricBackbone.name: GeometricBackbone,
    NetBackbone.name: NetBackbone,
    PrecomputedBackbone.name: PrecomputedBackbone,
}


def get_backbone(name: str = "geometric", **options: Any) -> Backbone:
    """The backbone called ``name``, built with ``options`` (see each class)."""
    if name not in BACKBONES:
        raise InputError(None, f"unknown backbone '{name}' (choose from {', '.join(BACKBONES)})")
    try:
        return BACKBONES[name](**options)
    except TypeError as e:
        raise InputError(None, f"backbone '{name}': {e}") from None
