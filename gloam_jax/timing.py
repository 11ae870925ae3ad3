"""Where a frame's time goes: wall-clock milliseconds per stage, for the run's report.

A :class:`StageTimer` adds up the stages of the frame in progress; the odometry files them
with the frame's status (``FrameStatus.stage_ms``) and starts the next frame from zero. The
stages, in the order a frame meets them:

* ``load``: reading the scan file and checking it (:mod:`gloam_jax.pipeline`'s prefetch
  thread, while the frame before registers);
* ``features``: the backbone's features, for the learned methods (the same thread; on the
  voxel grid, within ``voxels``, for a backbone that shares it);
* ``voxels``: cleaning, cropping, per-point times and the voxel grid (the same thread when the
  caller prepares the frame ahead, as ``gloam run`` does; else the registration's);
* ``deskew``: the voxel centres moved to the scan's reference time with the current velocity;
* ``neighbours``: the host's k-d trees: the scan's tree and k-NN for its covariances, each
  round's candidate query, the degeneracy check's nearest neighbours;
* ``covariances``: the jitted k-NN covariances and learned attributes, their transfers;
* ``solve``: the jitted GICP rounds, their transfers and the wait for their results, the
  host's convergence and degeneracy checks;
* ``map``: the keyframe decision, adding a keyframe and waiting for the local map's merge
  (the merge itself runs on a worker thread, beside the next frame's preprocessing);
* ``other``: the rest of the frame's registration (motion prediction, velocity, remapping).

JAX dispatches asynchronously: device work counts where its result is read (``np.asarray``),
which every stage above does before it ends, so no stage waits for another's device work.
"""

from __future__ import annotations

import time
from collections.abc import Iterable

import numpy as np

STAGES: tuple[str, ...] = (
    "load", "features", "voxels", "deskew", "neighbours", "covariances", "solve", "map", "other",
)  # fmt: skip


class _Span:
    __slots__ = ("timer", "stage", "start")

    def __init__(self, timer: StageTimer, stage: str) -> None:
        self.timer, self.stage = timer, stage

    def __enter__(self) -> None:
        self.start = time.perf_counter()

    def __exit__(self, *exc) -> None:
        ms = self.timer.ms
        ms[self.stage] = ms.get(self.stage, 0.0) + 1e3 * (time.perf_counter() - self.start)


class StageTimer:
    """Milliseconds per stage of the frame in progress: ``with timer("solve"): ...`` adds the
    block's wall time to its stage."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}  # timed here (inside the registration, after begin)
        self.elsewhere: dict[str, float] = {}  # before it, or on another thread

    def __call__(self, stage: str) -> _Span:
        return _Span(self, stage)

    def add(self, ms: dict[str, float]) -> None:
        """Add milliseconds per stage measured elsewhere (another thread's work for this
        frame: :func:`gloam_jax.pipeline.timed_input`)."""
        for stage, stage_ms in ms.items():
            self.elsewhere[stage] = self.elsewhere.get(stage, 0.0) + stage_ms

    def split(self, stage: str, inner: dict[str, float]) -> None:
        """Move the milliseconds of ``inner``'s stages, timed within ``stage``, out of it
        into their own (the backbone's features on the voxel grid, inside ``voxels``)."""
        for name, ms in inner.items():
            self.ms[stage] = max(self.ms.get(stage, 0.0) - ms, 0.0)
            self.ms[name] = self.ms.get(name, 0.0) + ms

    def begin(self) -> None:
        """The registration starts: what was timed so far (the caller's loading) lies
        outside it, as another thread's work does."""
        self.add(self.ms)
        self.ms = {}

    def take(self, total_ms: float | None = None) -> dict[str, float]:
        """Every stage's milliseconds so far (0 for those not met), to 0.01 ms, and back to
        zero; ``total_ms``: the registration's wall time (since :meth:`begin`), whose part
        outside the stages timed within it is ``other``."""
        ms, elsewhere, self.ms, self.elsewhere = self.ms, self.elsewhere, {}, {}
        if total_ms is not None:
            ms["other"] = max(total_ms - sum(ms.values()), 0.0)
        for stage, stage_ms in elsewhere.items():
            ms[stage] = ms.get(stage, 0.0) + stage_ms
        return {stage: round(ms.get(stage, 0.0), 2) for stage in STAGES}


def summarise(stage_ms: Iterable[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Median and 95th percentile (ms) of each stage over frames' ``stage_ms`` records (those
    without one, frames of older runs, left out); empty without any."""
    rows = [r for r in stage_ms if r]
    if not rows:
        return {}
    table = np.array([[r.get(stage, 0.0) for stage in STAGES] for r in rows])
    median, p95 = np.median(table, axis=0), np.percentile(table, 95, axis=0)
    return {
        stage: {"median": round(float(m), 2), "p95": round(float(p), 2)}
        for stage, m, p in zip(STAGES, median, p95, strict=True)
    }
