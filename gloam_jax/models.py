"""The model file: the two MLPs (:mod:`gloam_jax.learned`) with the frozen PCA, Algorithm 1's
eps, the backbone that makes the raw features, and how the model was made.

:func:`save_model` writes a :class:`GLOAMModel` as one ``.npz`` (arrays plus a JSON
``metadata`` entry), :func:`load_model` reads and checks it; ``"default"`` names the model
shipped with the package.
"""

from __future__ import annotations

import dataclasses
import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from gloam_jax.errors import InputError
from gloam_jax.features import Backbone, get_backbone
from gloam_jax.features.novelty import FeatureNovelty
from gloam_jax.features.pca import FeaturePCA
from gloam_jax.io import write_npz
from gloam_jax.learned import (
    DEFAULT_EPS,
    FEATURE_DIM,
    HIDDEN_DIM,
    MLP,
    OUTPUT_DIM,
    EigenvalueEstimationMLP,
    FeatureConversionMLP,
    Learned,
    check_method,
    plane_output,
)
from gloam_jax.sensor import SensorSignature

MODEL_FORMAT = "gloam-jax-model"
MODEL_VERSION = 1


@dataclass(frozen=True)
class GLOAMModel:
    """Everything that turns a raw scan into association features and covariances."""

    pca: FeaturePCA
    conversion: FeatureConversionMLP
    eigenvalue: EigenvalueEstimationMLP
    eps: float = DEFAULT_EPS
    backbone_name: str = "geometric"  # with backbone_options: see backbone()
    backbone_options: dict[str, Any] = field(default_factory=dict)
    version: int = MODEL_VERSION
    provenance: dict[str, Any] = field(default_factory=dict)  # how it was made (training)
    # Algorithm 1's planes at most this thick (smallest over middle eigenvalue; None: unbounded).
    max_thickness: float | None = None
    # The training features' region, which the MLPs' inputs are clamped to (None: unclamped).
    novelty: FeatureNovelty | None = None
    # The sensors of the training scans (gloam_jax.sensor); None: not recorded (older files).
    sensors: tuple[SensorSignature, ...] | None = None

    def __post_init__(self) -> None:
        problem = _thickness_problem(self.max_thickness, self.eps)
        if problem:
            raise InputError(None, problem)

    def pca_features(self, raw: np.ndarray | Array) -> np.ndarray | Array:
        """Backbone features (N, D) -> PCA features (N, 6), NumPy or JAX."""
        if raw.shape[-1] != self.pca.input_dim:
            raise InputError(
                None,
                f"features have {raw.shape[-1]} columns, the model's PCA expects "
                f"{self.pca.input_dim} (backbone '{self.backbone_name}')",
            )
        return self.pca.transform(raw)

    def backbone(self) -> Backbone:
        """The backbone that makes the raw features this model's PCA expects; InputError when
        its feature width (where it is known before a scan) is not the PCA's."""
        backbone = get_backbone(self.backbone_name, **self.backbone_options)
        width = getattr(backbone, "dim", None)
        if width is not None and width != self.pca.input_dim:
            raise InputError(
                None,
                f"the model's PCA expects {self.pca.input_dim} features per point, but its "
                f"backbone '{self.backbone_name}' gives {width}",
            )
        return backbone

    @property
    def learned(self) -> Learned:
        """Both MLPs, eps, the thickness bound and the novelty, as the registration takes them."""
        return Learned(
            self.conversion, self.eigenvalue, self.eps,
            max_thickness=self.max_thickness, novelty=self.novelty,
        )  # fmt: skip


def _thickness_problem(max_thickness: object, eps: float) -> str | None:
    """Why ``max_thickness`` is not a usable bound for a model with ``eps``, or None."""
    if max_thickness is None:
        return None
    if isinstance(max_thickness, bool) or not isinstance(max_thickness, int | float):
        return f"max_thickness must be a number or null, got {max_thickness!r}"
    if not eps <= max_thickness <= 1:
        # Below eps, GICP's own plane (eps, 1, 1) would not fit: the gicp start and the
        # fall-back to GICP would register otherwise.
        return f"max_thickness must be in [eps = {eps:g}, 1], got {max_thickness:g}"
    return None


INITS = ("random", "gicp")
CONVERSION_INIT_SCALE = 0.01  # init "gicp": association features of ~1 cm against metres


def init_model(
    key: Array,
    pca: FeaturePCA,
    *,
    eps: float = DEFAULT_EPS,
    backbone: str = "geometric",
    backbone_options: dict[str, Any] | None = None,
    init: str = "random",
    sensors: tuple[SensorSignature, ...] | None = None,
) -> GLOAMModel:
    """A model with initialised MLPs around a fitted PCA (on scans of ``sensors``).

    ``init="random"``: both MLPs as :meth:`MLP.init`. ``init="gicp"``: a start at plain GICP,
    for training. The eigenvalue MLP is constant at :func:`~gloam_jax.learned.plane_output`,
    so Algorithm 1 gives exactly GICP's plane, and keeps a gradient. The conversion MLP's
    output weights are scaled by
    :data:`CONVERSION_INIT_SCALE`: association features of centimetres, so association is
    xyz-nearest but for near ties. (Equal features would give it no gradient at all.)
    """
    if pca.components.shape[0] != FEATURE_DIM:
        raise InputError(
            None, f"the PCA must give {FEATURE_DIM} dimensions, not {pca.components.shape[0]}"
        )
    if not eps > 0:
        raise InputError(None, f"eps must be positive, got {eps}")
    if init not in INITS:
        raise InputError(None, f"unknown init '{init}' (choose from {', '.join(INITS)})")
    k_conv, k_eig = jax.random.split(key)
    conversion = FeatureConversionMLP.init(k_conv)
    eigenvalue = EigenvalueEstimationMLP.init(k_eig)
    if init == "gicp":
        conversion = conversion._replace(
            w2=CONVERSION_INIT_SCALE * conversion.w2, b2=jnp.zeros_like(conversion.b2)
        )
        eigenvalue = eigenvalue.constant(plane_output(eps))
    return GLOAMModel(
        pca=pca,
        conversion=conversion,
        eigenvalue=eigenvalue,
        eps=float(eps),
        backbone_name=backbone,
        backbone_options=dict(backbone_options or {}),
        provenance={"init": init},
        sensors=sensors,
    )


def with_mlps(
    model: GLOAMModel,
    conversion: MLP,
    eigenvalue: MLP,
    provenance: dict[str, Any] | None = None,
) -> GLOAMModel:
    """``model`` with new MLP weights (trained ones), and what made them."""
    return dataclasses.replace(
        model,
        conversion=FeatureConversionMLP(*(jnp.asarray(x, jnp.float32) for x in conversion)),
        eigenvalue=EigenvalueEstimationMLP(*(jnp.asarray(x, jnp.float32) for x in eigenvalue)),
        provenance=dict(provenance or model.provenance),
    )


def learned_parts(model: GLOAMModel | None, method: str) -> Learned:
    """The parts of ``model`` that ``method`` (a key of :data:`~gloam_jax.learned.METHODS`)
    uses; plain GICP needs no model."""
    if any(check_method(method)) and model is None:
        raise InputError(
            None, f"method '{method}' needs a model file (--weights FILE, or 'default')"
        )
    if model is None:
        return Learned()
    return model.learned.for_method(method)


def _arrays(model: GLOAMModel) -> dict[str, np.ndarray]:
    out = {f"pca_{k}": np.asarray(v, np.float64) for k, v in model.pca._asdict().items()}
    for prefix, mlp in (("conversion", model.conversion), ("eigenvalue", model.eigenvalue)):
        out.update({f"{prefix}_{k}": np.asarray(v, np.float32) for k, v in mlp._asdict().items()})
    if model.novelty is not None:
        novelty = model.novelty._asdict().items()
        out.update({f"novelty_{k}": np.asarray(v, np.float64) for k, v in novelty})
    return out


def save_model(path: str | os.PathLike[str], model: GLOAMModel) -> None:
    """Write the model as one ``.npz`` (arrays and a JSON ``metadata`` entry), atomically."""
    options = model.backbone_options
    weights = options.get("weights")
    if isinstance(weights, str) and Path(weights).is_file():
        if Path(weights).resolve().parent == Path(path).resolve().parent:
            # A network beside the file stays named relative to it (load_model resolves it), so
            # a rewritten file (a test score appended) still loads from any working directory.
            options = {**options, "weights": Path(weights).name}
    metadata = {
        "format": MODEL_FORMAT,
        "version": model.version,
        "eps": model.eps,
        "backbone": model.backbone_name,
        "backbone_options": options,
        "provenance": model.provenance,
        # Written only when set, so that a file without the bound reads as it always did.
        **({} if model.max_thickness is None else {"max_thickness": model.max_thickness}),
        **({} if model.sensors is None else {"sensors": [s.to_dict() for s in model.sensors]}),
    }
    # A 0-d unicode array, not a pickled object: the file loads with allow_pickle=False.
    write_npz(path, metadata=np.array(json.dumps(metadata)), **_arrays(model))


_NOVELTY_SHAPES = {"novelty_mean": (FEATURE_DIM,), "novelty_factor": (FEATURE_DIM, FEATURE_DIM),
                   "novelty_radius2": ()}  # fmt: skip


def _expected_shapes(d: int, novelty: bool) -> dict[str, tuple[int, ...]]:
    """Every array of a model file and its shape, for PCA input width ``d``; ``novelty``: the
    file has a feature region (all of its arrays, or none)."""
    shapes = {
        "pca_mean": (d,),
        "pca_scale": (d,),
        "pca_components": (FEATURE_DIM, d),
        "pca_explained_variance_ratio": (FEATURE_DIM,),
    }
    for prefix in ("conversion", "eigenvalue"):
        shapes |= {
            f"{prefix}_w1": (FEATURE_DIM, HIDDEN_DIM),
            f"{prefix}_b1": (HIDDEN_DIM,),
            f"{prefix}_w2": (HIDDEN_DIM, OUTPUT_DIM),
            f"{prefix}_b2": (OUTPUT_DIM,),
        }
    return shapes | _NOVELTY_SHAPES if novelty else shapes


SHIPPED = "default"
"""The name that :func:`load_model` (and ``--weights``, ``model:`` in configs) resolves to the
model trained and shipped with the package (``gloam_jax/data/gloam_default.npz``)."""
# Every shipped model by name, in the order ``model: default`` tries them against the scans'
# sensor (gloam_jax/guard.py): "hdl64" first (configs/train_hdl64.yaml, chosen on the
# KITTI-length validation worlds, where it beats the protocol's model on HDL-64 scans), then
# the protocol's model (HDL-64 and VLP-16); "net" is GLOAM on the net backbone
# (configs/gloam_net.yaml; trained by configs/train_net.yaml, chosen on the long validation
# worlds: experiments/net_long).
SHIPPED_MODELS = {"hdl64": "gloam_hdl64.npz", SHIPPED: "gloam_default.npz", "net": "gloam_net.npz"}


def shipped_model_path(name: str = SHIPPED) -> Path:
    """Path of a shipped model file (its provenance records how it was trained)."""
    return Path(__file__).resolve().parent / "data" / SHIPPED_MODELS[name]


def load_model(path: str | os.PathLike[str]) -> GLOAMModel:
    """Read a file written by :func:`save_model` (or a name of :data:`SHIPPED_MODELS`: a
    shipped model); a bad file is a one-line InputError."""
    p = shipped_model_path(str(path)) if str(path) in SHIPPED_MODELS else Path(path)
    if not p.is_file():
        raise InputError(p, "model file not found")
    try:
        npz = np.load(p, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(p, f"not a gloam-jax model file ({e})") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise InputError(p, "not a gloam-jax model file (an .npy array, not an .npz)")
    try:
        with npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(p, f"not a gloam-jax model file ({e})") from None
    try:
        metadata = json.loads(str(arrays.pop("metadata")))
    except (KeyError, json.JSONDecodeError):
        raise InputError(p, "not a gloam-jax model file (no JSON metadata)") from None
    if not isinstance(metadata, dict) or metadata.get("format") != MODEL_FORMAT:
        raise InputError(p, "not a gloam-jax model file (metadata has no gloam-jax format tag)")
    if metadata.get("version") != MODEL_VERSION:
        raise InputError(
            p,
            f"model format version {metadata.get('version')} is not supported "
            f"(this gloam-jax reads version {MODEL_VERSION})",
        )
    novelty = any(name in arrays for name in _NOVELTY_SHAPES)
    expected = _expected_shapes(arrays["pca_mean"].size if "pca_mean" in arrays else 0, novelty)
    for name, shape in expected.items():
        if name not in arrays:
            raise InputError(p, f"model file has no '{name}' array")
        if arrays[name].dtype.kind not in "fi":
            raise InputError(p, f"'{name}' is not numeric (dtype {arrays[name].dtype})")
        if arrays[name].shape != shape:
            raise InputError(p, f"'{name}' has shape {arrays[name].shape}, expected {shape}")
        if not np.all(np.isfinite(arrays[name])):
            raise InputError(p, f"'{name}' contains NaN or infinite values")
    if not np.all(arrays["pca_scale"] > 0):
        raise InputError(p, "'pca_scale' must be positive (it divides the features)")
    if novelty and not arrays["novelty_radius2"] > 0:
        raise InputError(p, "'novelty_radius2' must be positive")
    eps = metadata.get("eps")
    if isinstance(eps, bool) or not isinstance(eps, int | float) or not eps > 0:
        raise InputError(p, f"eps must be a positive number, got {eps!r}")
    backbone, options = metadata.get("backbone"), metadata.get("backbone_options")
    if not isinstance(backbone, str) or not isinstance(options, dict):
        raise InputError(p, "metadata needs a backbone name and a backbone_options object")
    weights = options.get("weights")
    if isinstance(weights, str) and (p.parent / weights).is_file() and weights != "default":
        # A network file beside the model (a fine-tuned backbone), named relative to it.
        options = {**options, "weights": str(p.parent / weights)}
    provenance = metadata.get("provenance", {})
    if not isinstance(provenance, dict):
        raise InputError(p, "metadata 'provenance' must be an object")
    max_thickness = metadata.get("max_thickness")
    problem = _thickness_problem(max_thickness, eps)
    if problem:
        raise InputError(p, problem)
    sensors = _sensors(p, metadata.get("sensors"))

    def mlp(cls: type[MLP], prefix: str) -> MLP:
        return cls(*(jnp.asarray(arrays[f"{prefix}_{k}"]) for k in MLP._fields))

    return GLOAMModel(
        pca=FeaturePCA(*(arrays[f"pca_{k}"] for k in FeaturePCA._fields)),
        conversion=mlp(FeatureConversionMLP, "conversion"),
        eigenvalue=mlp(EigenvalueEstimationMLP, "eigenvalue"),
        eps=float(eps),
        backbone_name=backbone,
        backbone_options=options,
        version=MODEL_VERSION,
        provenance=provenance,
        max_thickness=None if max_thickness is None else float(max_thickness),
        novelty=(
            FeatureNovelty(
                arrays["novelty_mean"], arrays["novelty_factor"], float(arrays["novelty_radius2"])
            )
            if novelty
            else None
        ),  # fmt: skip
        sensors=sensors,
    )


def _sensors(path: Path, record: object) -> tuple[SensorSignature, ...] | None:
    """The metadata's ``sensors`` list read (None where the file has none); InputError
    naming ``path`` when it is malformed."""
    if record is None:
        return None
    if not isinstance(record, list):
        raise InputError(path, f"metadata 'sensors' must be a list, not {record!r}")
    try:
        return tuple(SensorSignature.from_dict(s) for s in record)
    except InputError as err:
        raise InputError(path, f"metadata 'sensors': {err.problem}") from None
