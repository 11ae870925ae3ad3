"""Training: differentiable trajectory losses (:mod:`gloam_jax.training.losses`)."""

from __future__ import annotations

from gloam_jax.training.losses import (
    TRAINING_FRACTIONS,
    SegmentPlan,
    chain,
    relative_rotation_error,
    relative_translation_error,
    scaled_lengths,
    segment_errors,
    segment_plan,
)

__all__ = [
    "TRAINING_FRACTIONS",
    "SegmentPlan",
    "chain",
    "relative_rotation_error",
    "relative_translation_error",
    "scaled_lengths",
    "segment_errors",
    "segment_plan",
]
