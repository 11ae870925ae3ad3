"""Training settings: what to train on, how to register, and each mode's own knobs.

A ``configs/train_*.yaml`` file holds the fields of :class:`TrainConfig`; the nested
``preprocess`` (range crop, voxel size, k-NN, regulariser: as the odometry's), ``batch``
(registrations, with their ``gicp`` settings), ``tpe`` and ``grad`` sections take the fields
of their classes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from gloam_jax.errors import InputError
from gloam_jax.preprocess import PreprocessConfig
from gloam_jax.training.batch import BatchConfig
from gloam_jax.training.protocol import TRAIN_SEQUENCES


@dataclass(frozen=True)
class TPEConfig:
    """The paper's black-box search: optuna's TPE over every MLP weight."""

    n_trials: int = 200  # finished (complete or pruned) trials of the study, all workers together
    n_startup_trials: int = 10  # random trials before TPE models the good ones
    bound: float = 1.0  # each weight searched in [init - bound, init + bound]
    validate_best: int = 10  # with validation sequences: this many best trials are validated
    storage: str | None = None  # optuna RDB URL; None: sqlite:///RUN/study.db
    study_name: str | None = None  # None: the run folder's name
    # A worker marks its running trial alive every heartbeat_interval s; a trial silent for
    # grace_period s (its worker was killed) is failed and its weights queued again.
    heartbeat_interval: int = 30
    grace_period: int = 120

    def __post_init__(self) -> None:
        for name in ("n_trials", "validate_best", "heartbeat_interval", "grace_period"):
            if getattr(self, name) < 1:
                raise InputError(None, f"tpe.{name} must be >= 1, not {getattr(self, name)}")
        if self.grace_period <= self.heartbeat_interval:
            raise InputError(
                None,
                f"tpe.grace_period ({self.grace_period} s) must be longer than "
                f"tpe.heartbeat_interval ({self.heartbeat_interval} s)",
            )


@dataclass(frozen=True)
class GradConfig:
    """Gradient descent through the registrations (optax Adam)."""

    steps: int = 40
    learning_rate: float = 0.02
    clip_norm: float = 1.0  # global gradient norm clip
    # Steps over which every Adam rate rises linearly from 0 to its value; 0: full rate from the
    # first step. Adam's first steps move each weight by about the full rate whatever the
    # gradient's size, which from the exact GICP start is large against the eps floor.
    warmup_steps: int = 0
    eval_every: int = 2  # steps between hard-association evaluations of the training loss
    checkpoint_every: int = 1  # steps between checkpoints
    # Source points per pair in a step: a fresh random subset of the prepared ones each step
    # (stochastic gradients, cheaper steps); None: all. Evaluations always use all.
    source_points: int | None = None
    # Fine-tune the net backbone's last layer with the MLPs, at this Adam learning rate
    # (gloam_jax.training.head); None: the backbone stays frozen.
    head_learning_rate: float | None = None

    def __post_init__(self) -> None:
        if self.source_points is not None and self.source_points < 1:
            raise InputError(None, f"grad.source_points must be >= 1, not {self.source_points}")
        if self.warmup_steps < 0:
            raise InputError(None, f"grad.warmup_steps must be >= 0, not {self.warmup_steps}")
        if self.head_learning_rate is not None and not self.head_learning_rate > 0:
            raise InputError(
                None, f"grad.head_learning_rate must be positive, not {self.head_learning_rate}"
            )


@dataclass(frozen=True)
class TrainConfig:
    """A training run: data, model start, registrations, and the chosen mode's settings."""

    mode: Literal["tpe", "grad"] = "grad"  # the paper's TPE search, or gradients through GICP
    method: Literal["gicp_da", "gicp_ce", "gloam"] = "gloam"  # which MLPs are trained
    # KITTI-layout root of the training sequences, or a list of roots (simulation seeds of the
    # same worlds): every listed sequence of every root is a training window.
    data: str | tuple[str, ...] = "data/protocol"
    sequences: tuple[str, ...] = TRAIN_SEQUENCES  # training sequences of data
    frames: int | None = None  # first N scans of each sequence (None: all)
    init_model: str | None = None  # start from this model file (its PCA and MLPs)
    init: Literal["random", "gicp"] = "gicp"  # without init_model: how the MLPs start
    # Without init_model: the feature backbone whose PCA is fitted (net: backbone_weights).
    backbone: Literal["geometric", "net"] = "geometric"
    # net: a shipped network's name (features.net.SHIPPED_NETS) or a train-backbone file.
    backbone_weights: str = "default"
    # More options of that backbone (its class's keyword arguments; geometric: voxel_size,
    # scales, intensity_scale, max_height, drop, min_range, max_range: with the
    # preprocessing's voxel size and range band it runs on the odometry's own voxel grid;
    # net: grid, {resolution, min_range, max_range, k}, likewise).
    backbone_options: dict[str, Any] = field(default_factory=dict)
    pca_every: int = 25  # without init_model: fit the PCA on every N-th training scan
    seed: int = 0  # of the start model, TPE's sampler and the point subsets
    # What is minimised and selected on (gloam_jax.training.objective): "t_err", the windows'
    # mean; "gicp_ratio", each window's t_err over plain GICP's, averaged, plus worse_penalty
    # times the mean excess of the windows made worse than GICP.
    objective: Literal["t_err", "gicp_ratio"] = "t_err"
    worse_penalty: float = 4.0  # gicp_ratio: weight of the windows' excess over GICP
    # The exported weights are the best on these validation sequences of validation_data
    # (None: the roots of data) among the candidates (TPE: its best tpe.validate_best trials;
    # gradients: every evaluated step); none: the best on the training windows. Never test
    # sequences.
    validation: tuple[str, ...] = ()
    # KITTI-layout root of the validation sequences, or a list of roots (simulation seeds of
    # the same worlds): each is scored on its own and the worst one chooses, so that a choice
    # must hold on every draw, not on their average.
    validation_data: str | tuple[str, ...] | None = None
    # With validation: the chosen weights ship only if their validation objective is below plain
    # GICP's by this fraction, else plain GICP ships (training.problem.choose). The gicp start
    # scores within 0.5 % of GICP on validation (its association features differ by ~1 cm).
    min_gain: float = 0.01
    # Algorithm 1's planes at most this thick (smallest over middle eigenvalue, in [eps, 1]),
    # in training and in the exported model; None: the start model's bound (none unless
    # init_model has one). GICP's plane is 0.001 thick.
    max_thickness: float | None = None
    preprocess: PreprocessConfig = field(default_factory=PreprocessConfig)
    batch: BatchConfig = field(default_factory=BatchConfig)
    tpe: TPEConfig = field(default_factory=TPEConfig)
    grad: GradConfig = field(default_factory=GradConfig)

    MOVED: ClassVar[dict[str, str]] = {"odometry": "preprocess"}

    def __post_init__(self) -> None:
        if self.backbone_weights != "default" and self.backbone != "net":
            raise InputError(None, "backbone_weights chooses the net backbone's network; "
                             f"this run's backbone is '{self.backbone}'")  # fmt: skip
        if not isinstance(self.backbone_options, dict):
            raise InputError(
                None, f"backbone_options must be a mapping, not {self.backbone_options!r}"
            )
        if self.worse_penalty < 0:
            raise InputError(None, f"worse_penalty must be >= 0, not {self.worse_penalty}")
        if not 0 <= self.min_gain < 1:
            raise InputError(None, f"min_gain must be in [0, 1), not {self.min_gain}")
        if self.max_thickness is not None and not 0 < self.max_thickness <= 1:
            raise InputError(None, f"max_thickness must be in (0, 1], not {self.max_thickness}")
        object.__setattr__(self, "data", as_roots(self.data, "data"))
        if self.validation_data is not None:
            object.__setattr__(
                self, "validation_data", as_roots(self.validation_data, "validation_data")
            )
        same_root = set(self.training_roots) & set(self.validation_roots)
        shared = sorted(set(self.validation) & set(self.sequences)) if same_root else []
        if shared:
            raise InputError(
                None, f"validation sequences {', '.join(shared)} are also training sequences"
            )

    @property
    def training_roots(self) -> tuple[str, ...]:
        """The roots that hold the training sequences."""
        return (self.data,) if isinstance(self.data, str) else self.data

    @property
    def validation_roots(self) -> tuple[str, ...]:
        """The roots that hold the validation sequences: validation_data, or data's."""
        roots = self.validation_data
        if roots is None:
            return self.training_roots
        return (roots,) if isinstance(roots, str) else roots


def as_roots(value: object, name: str) -> str | tuple[str, ...]:
    """``value`` as one root (a string) or a non-empty tuple of them; a one-line error
    naming ``name`` otherwise."""
    if isinstance(value, list | tuple):
        value = tuple(value)
        if value and all(isinstance(r, str) for r in value):
            return value
    elif isinstance(value, str):
        return value
    raise InputError(None, f"{name} must be a root or a non-empty list of roots, not {value!r}")
