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
    "intensity_warning",
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


# How far a scan's mean intensity may stray from the fitted one before a run says so: a
# factor that catches other units (0-255, 0-65535 counts against 0-1), not subtler shifts.
INTENSITY_FACTOR = 3.0


def intensity_warning(backbone: Backbone, pca: FeaturePCA, scan: np.ndarray) -> str | None:
    """One line when ``scan`` (N, 3+) has no intensity or a mean intensity more than
    INTENSITY_FACTOR from the one ``backbone``'s learned features were fitted on (for a
    network that reads intensity ranks: no intensity, or one value throughout); None
    otherwise, and for backbones that read no intensity."""
    values = scan[:, 3][np.isfinite(scan[:, 3])] if scan.shape[1] > 3 else None
    if getattr(backbone, "reads_intensity_order", False):
        if values is not None and len(values) and values.min() < values.max():
            return None
        return (f"the scans carry no intensity (none, or one value), but the '{backbone.name}' "
                "features read its order in each scan; the learned parts may not hold")  # fmt: skip
    fitted = getattr(backbone, "fitted_intensity", lambda _: None)(pca)
    if fitted is None or not fitted > 0:
        return None
    where = f"the '{backbone.name}' features were fitted on a mean intensity of {fitted:.3g}"
    if values is None:
        return f"the scans carry no intensity, but {where}; the learned parts may not hold"
    mean = float(values.mean()) if len(values) else 0.0
    if fitted / INTENSITY_FACTOR <= mean <= fitted * INTENSITY_FACTOR:
        return None
    return (f"the scans' mean intensity is {mean:.3g}, but {where} (other units?); the learned "
            "parts may not hold")  # fmt: skip


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
