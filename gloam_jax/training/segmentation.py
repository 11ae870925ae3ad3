"""Training the ``net`` backbone's segmentation network (``gloam train-backbone``).

Training scans are voxelised once (voxel label: the majority class of its points); each step
draws ``batch`` crops of the ``crop`` voxels nearest a random voxel of a random scan (a fixed
shape: nothing recompiles), and takes an Adam step on the class-weighted cross-entropy
(weights ``1 / sqrt(class frequency)``, RandLA-Net's). Held-out scans are scored on their raw
points through the same path as the backbone (:func:`gloam_jax.features.net.run_scan`): per-class
IoU and mIoU over the classes present. Checkpoints after every ``eval_every`` steps; a rerun
with the same folder resumes, with the same draws as an uninterrupted run.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from scipy.spatial import cKDTree

from gloam_jax import io
from gloam_jax.errors import InputError
from gloam_jax.features.net import (
    CLASSES,
    NetConfig,
    NetInputs,
    SegNet,
    build_inputs,
    class_index,
    run_scan,
    save_net,
    scan_intensity,
    voxelize,
)
from gloam_jax.io.kitti import KittiSequence
from gloam_jax.training.grad import load_checkpoint, save_checkpoint
from gloam_jax.training.problem import Clock, write_history

CHECKPOINT = "checkpoint.npz"
WEIGHTS = "net.npz"


@dataclasses.dataclass(frozen=True)
class SegmentationConfig:
    """What ``gloam train-backbone`` trains on and how; a resumed run must match."""

    data: str
    train: tuple[str, ...]
    test: tuple[str, ...]
    steps: int = 2000
    batch: int = 4
    crop: int = 4096  # voxels per crop
    learning_rate: float = 3e-3
    eval_every: int = 250
    test_every: int = 2  # score every n-th held-out scan
    seed: int = 0
    net: NetConfig = NetConfig()


@dataclasses.dataclass
class LabelledScan:
    """A voxelised training scan: xyz (M, 3), intensity (M,), class (M,) (-1: none), tree."""

    xyz: np.ndarray
    intensity: np.ndarray
    label: np.ndarray
    tree: cKDTree


def _sequence(root: str, seq: str) -> KittiSequence:
    s = KittiSequence(root, seq)
    if len(s) == 0 or s.labels(0) is None:
        raise InputError(s.sequence_dir, "no labelled scans (labels/NNNNNN.label)")
    return s


def load_training_scans(cfg: SegmentationConfig, progress=None) -> list[LabelledScan]:
    """Every training scan, voxelised at the network's voxel size, with voxel labels."""
    out = []
    seqs = [_sequence(cfg.data, s) for s in cfg.train]
    total = sum(len(s) for s in seqs)
    for seq in seqs:
        for i in range(len(seq)):
            scan = seq.scan(i)
            finite = np.all(np.isfinite(scan[:, :3]), axis=1)
            xyz, intensity, inverse = voxelize(scan[finite], cfg.net.voxel_size)
            intensity = scan_intensity(intensity, cfg.net)
            cls = class_index(seq.labels(i)[finite])
            # Majority vote per voxel over labelled points (class -1 counts in no column).
            votes = np.zeros((len(xyz), len(CLASSES)), np.int32)
            ok = cls >= 0
            np.add.at(votes, (inverse[ok], cls[ok]), 1)
            label = np.where(votes.any(axis=1), votes.argmax(axis=1), -1).astype(np.int32)
            out.append(LabelledScan(xyz, intensity, label, cKDTree(xyz)))
            if progress:
                progress("voxelising training scans", len(out), total)
    return out


def class_weights(scans: list[LabelledScan]) -> np.ndarray:
    """Weights (C,) ``1 / sqrt(frequency)``, mean 1 over the classes present, 0 for absent."""
    counts = np.bincount(np.concatenate([s.label[s.label >= 0] for s in scans]),
                         minlength=len(CLASSES)).astype(np.float64)  # fmt: skip
    present = counts > 0
    w = np.where(present, 1.0 / np.sqrt(np.maximum(counts, 1) / counts.sum()), 0.0)
    return (w / w[present].mean()).astype(np.float32)


def draw_batch(
    scans: list[LabelledScan], cfg: SegmentationConfig, step: int
) -> tuple[NetInputs, np.ndarray]:
    """Crops (B stacked :class:`NetInputs`) and their labels (B, crop), fixed by seed and step."""
    rng = np.random.default_rng([cfg.seed, step])
    crops, labels = [], []
    for _ in range(cfg.batch):
        s = scans[rng.integers(len(scans))]
        k = min(cfg.crop, len(s.xyz))
        _, idx = s.tree.query(s.xyz[rng.integers(len(s.xyz))], k=k)
        idx = np.sort(np.atleast_1d(idx))
        crops.append(build_inputs(s.xyz[idx], s.intensity[idx], cfg.net, size=cfg.crop))
        labels.append(np.pad(s.label[idx], (0, cfg.crop - k), constant_values=-1))
    batch = NetInputs(*(np.stack(parts) for parts in zip(*crops, strict=True)))
    return batch, np.stack(labels)


def weighted_cross_entropy(
    net: SegNet, x: NetInputs, labels: jax.Array, weights: jax.Array
) -> jax.Array:
    """Class-weighted mean cross-entropy over labelled voxels of a batch (B, N) of crops."""
    logits = jax.vmap(lambda xi: net(xi, chunked=False)[1])(x)  # (B, N, C)
    valid = labels >= 0
    y = jnp.where(valid, labels, 0)
    nll = -jnp.take_along_axis(jax.nn.log_softmax(logits), y[..., None], axis=-1)[..., 0]
    w = jnp.where(valid, weights[y], 0.0)
    return jnp.sum(w * nll) / jnp.maximum(jnp.sum(w), 1e-9)


def make_optimizer(cfg: SegmentationConfig) -> optax.GradientTransformation:
    schedule = optax.cosine_decay_schedule(cfg.learning_rate, cfg.steps, alpha=0.05)
    return optax.chain(optax.clip_by_global_norm(1.0), optax.adam(schedule))


def make_step(optimizer: optax.GradientTransformation):
    """The jitted Adam step: (params, static, opt_state, x, labels, weights) -> (..., loss)."""

    @eqx.filter_jit
    def step(params, static, opt_state, x, labels, weights):
        def loss_fn(p):
            return weighted_cross_entropy(eqx.combine(p, static), x, labels, weights)

        loss, grads = jax.value_and_grad(loss_fn)(params)
        updates, opt_state = optimizer.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    return step


def evaluate(
    net: SegNet,
    root: str,
    sequences: tuple[str, ...],
    every: int = 1,
    transform: Callable[[np.ndarray], np.ndarray] | None = None,
) -> dict[str, Any]:
    """Per-class IoU and mIoU on the raw points of every ``every``-th scan of ``sequences``
    (each passed through ``transform`` first, when given: row-aligned, (N, 4) -> (N, 4));
    the mean is over the classes with ground-truth points."""
    c = len(CLASSES)
    confusion = np.zeros((c, c), np.int64)
    scans = 0
    for name in sequences:
        seq = _sequence(root, name)
        for i in range(0, len(seq), every):
            scan = seq.scan(i) if transform is None else transform(seq.scan(i))
            confusion += confusion_matrix(seq.labels(i), run_scan(net, scan)[1].argmax(axis=1))
            scans += 1
    return {**iou_scores(confusion), "scans": scans}


def confusion_matrix(labels: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    """(C, C) counts, truth by row, of SemanticKITTI ids ``labels`` (N,) against predicted
    training classes (N,); unlabeled and unknown ids, and unpredicted rows (-1), left out."""
    c = len(CLASSES)
    truth = class_index(labels)
    ok = (truth >= 0) & (predicted >= 0)
    return np.bincount(truth[ok] * c + predicted[ok], minlength=c * c).reshape(c, c)


def iou_scores(confusion: np.ndarray) -> dict[str, Any]:
    """Per-class IoU, their mean over the classes with ground-truth points, and the share of
    points classed right."""
    tp = np.diag(confusion).astype(np.float64)
    union = confusion.sum(0) + confusion.sum(1) - tp
    present = np.flatnonzero(confusion.sum(1) > 0)
    iou = {CLASSES[j]: float(tp[j] / union[j]) for j in present}
    miou = float(np.mean(list(iou.values()))) if iou else float("nan")
    points = int(confusion.sum())
    accuracy = float(tp.sum() / points) if points else float("nan")
    return {"miou": miou, "iou": iou, "accuracy": accuracy, "points": points}


def plot_curve(history: list[dict[str, Any]], path: Path) -> None:
    """Training loss and held-out mIoU against steps, one figure."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    steps = [h["step"] for h in history]
    ax.plot(steps, [h["loss"] for h in history], color="C0", marker=".")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss (weighted cross-entropy)", color="C0")
    ax.grid(alpha=0.3)
    right = ax.twinx()
    right.plot(steps, [100 * h["miou"] for h in history], color="C1", marker=".")
    right.set_ylabel("held-out mIoU (%)", color="C1")
    right.set_ylim(0, 100)
    fig.tight_layout()
    io.write_figure(path, fig, dpi=120)
    plt.close(fig)


def _settings(cfg: SegmentationConfig) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def train_segmentation(
    cfg: SegmentationConfig,
    out: str | Path,
    progress: Callable[..., None] | None = None,
) -> tuple[SegNet, dict[str, Any]]:
    """Train (or resume) in ``out``; writes ``net.npz``, ``history.json``, ``curve.png`` and
    returns the network and its provenance. ``progress(label, done, total, **fields)``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    settings_file = out / "settings.json"
    if settings_file.exists():
        # Only ``steps`` may change on a resume: fewer ends the run at its last checkpoint;
        # more continues it (the learning rate's cosine follows the new length).
        old, new = json.loads(settings_file.read_text()), _settings(cfg)
        changed = [k for k in new if k != "steps" and old.get(k) != new[k]]
        if changed:
            raise InputError(settings_file, f"this run was started with other {', '.join(changed)}")
    io.write_atomic(settings_file, json.dumps(_settings(cfg), indent=1))

    scans = load_training_scans(cfg, progress)
    weights = jnp.asarray(class_weights(scans))
    params, static = eqx.partition(SegNet(cfg.net, key=jax.random.key(cfg.seed)), eqx.is_array)
    optimizer = make_optimizer(cfg)
    opt_state = optimizer.init(params)
    history: list[dict[str, Any]] = []
    step, clock = 0, Clock()
    if (out / CHECKPOINT).exists():
        trees, meta = load_checkpoint(out / CHECKPOINT, {"params": params, "opt": opt_state})
        params, opt_state = trees["params"], trees["opt"]
        step, history, clock = meta["step"], meta["history"], Clock(meta["elapsed"])
    update = make_step(optimizer)
    losses: list[float] = []
    while step < cfg.steps:
        x, labels = draw_batch(scans, cfg, step)
        params, opt_state, loss = update(params, static, opt_state, x, labels, weights)
        losses.append(float(loss))
        step += 1
        if step % cfg.eval_every == 0 or step == cfg.steps:
            scores = evaluate(eqx.combine(params, static), cfg.data, cfg.test, cfg.test_every)
            history.append({"step": step, "loss": float(np.mean(losses)), "miou": scores["miou"],
                            "iou": scores["iou"], "wall_s": clock.lap()})  # fmt: skip
            losses = []
            meta = {"step": step, "history": history, "elapsed": clock.elapsed}
            save_checkpoint(out / CHECKPOINT, {"params": params, "opt": opt_state}, meta)
            write_history(out, history)
            plot_curve(history, out / "curve.png")
        if progress:
            last = history[-1]["miou"] if history else float("nan")
            progress("training steps", step, cfg.steps,
                     rate=f"loss {float(loss):.3f}, held-out mIoU {100 * last:.1f} %")  # fmt: skip
    net = eqx.combine(params, static)
    final = evaluate(net, cfg.data, cfg.test)
    provenance = {
        "settings": _settings(cfg),
        "training_scans": len(scans),
        "class_weights": dict(zip(CLASSES, map(float, weights), strict=True)),
        "steps": step,
        "wall_s": history[-1]["wall_s"] if history else 0.0,
        "test": final,
    }
    save_net(out / WEIGHTS, net, provenance)
    io.write_atomic(out / "metrics.json", json.dumps(final, indent=1))
    return net, provenance
