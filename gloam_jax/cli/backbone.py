"""``gloam train-backbone`` and ``gloam segment``: the ``net`` backbone's segmentation network,
trained on labelled scans, and its classes for any scans."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer

from gloam_jax.cli.common import (
    DataArg,
    SequenceOpt,
    StartOpt,
    StrideOpt,
    Tasks,
    TopicOpt,
    app,
    console,
    frame_progress,
    progress_bar,
    user_errors,
    write_json,
)
from gloam_jax.errors import InputError


def _ids(text: str) -> tuple[str, ...]:
    return tuple(s.strip() for s in text.split(",") if s.strip())


def _shape(widths: str | None, embed: int | None) -> dict:
    """NetConfig's ``widths`` and ``embed`` where given (a bad --widths is an InputError)."""
    shape: dict = {} if embed is None else {"embed": embed}
    if widths is not None:
        try:
            shape["widths"] = tuple(int(w) for w in _ids(widths))
        except ValueError:
            shape["widths"] = ()
        if len(shape["widths"]) != 3 or min(shape["widths"]) < 2:
            raise InputError(None, f"--widths needs three channel counts of at least 2, "
                                   f"not {widths!r}")  # fmt: skip
    return shape


@app.command(
    name="train-backbone",
    epilog=(
        "Example:\n\n"
        "  python scripts/simulate_backbone_data.py --out data/backbone\n\n"
        "  gloam train-backbone data/backbone --train 00,01,02 --test 20,21 --out runs/net\n\n"
        "Rerunning the same command with the same --out resumes it from its last checkpoint; "
        "only --steps may change: fewer ends the run there (weights and scores written), "
        "more continues it."
    ),
)
@user_errors
def train_backbone(
    data: Annotated[Path, typer.Argument(help="KITTI-layout root with labels/ per sequence.")],
    train: Annotated[str, typer.Option(help="Training sequence ids, comma-separated.")],
    test: Annotated[str, typer.Option(help="Held-out sequence ids, comma-separated.")],
    out: Annotated[Path, typer.Option(help="Run folder (resumed when it exists).")] = Path(
        "runs/net"
    ),
    steps: Annotated[int, typer.Option(min=1, help="Adam steps.")] = 2000,
    batch: Annotated[int, typer.Option(min=1, help="Crops per step.")] = 4,
    crop: Annotated[int, typer.Option(min=64, help="Voxels per crop.")] = 4096,
    learning_rate: Annotated[float, typer.Option(min=0.0, help="Adam's start rate.")] = 3e-3,
    eval_every: Annotated[
        int, typer.Option(min=1, help="Score held-out scans and checkpoint every N steps.")
    ] = 250,
    test_every: Annotated[
        int, typer.Option(min=1, help="During training, score every N-th held-out scan.")
    ] = 2,
    seed: Annotated[int, typer.Option(help="Initialisation and crop seed.")] = 0,
    intensity: Annotated[
        bool, typer.Option(help="Feed intensity (--no-intensity: geometry only, other sensors).")
    ] = True,
    intensity_rank: Annotated[
        bool, typer.Option(help="Feed intensity as its rank in the scan (blind to its units).")
    ] = False,
    widths: Annotated[
        str | None,
        typer.Option(
            help="Channels of the stem, level 0 and level 1, comma-separated (default 8,32,64)."
        ),
    ] = None,
    embed: Annotated[
        int | None, typer.Option(min=1, help="Channels of the embedding (default 32).")
    ] = None,
) -> None:
    """Train the segmentation network whose per-point embedding is the ``net`` backbone."""
    from gloam_jax.features.net import NetConfig
    from gloam_jax.training.segmentation import WEIGHTS, SegmentationConfig, train_segmentation

    cfg = SegmentationConfig(
        data=str(data), train=_ids(train), test=_ids(test), steps=steps, batch=batch, crop=crop,
        learning_rate=learning_rate, eval_every=eval_every, test_every=test_every, seed=seed,
        net=NetConfig(intensity=intensity, intensity_rank=intensity_rank,
                      **_shape(widths, embed)),
    )  # fmt: skip
    with progress_bar() as bar:
        _, provenance = train_segmentation(cfg, out, Tasks(bar))
    scores = provenance["test"]
    for name, iou in scores["iou"].items():
        console.print(f"  {name:16s} IoU {100 * iou:5.1f} %")
    console.print(
        f"held-out mIoU {100 * scores['miou']:.1f} % over {scores['scans']} scans "
        f"({provenance['steps']} steps, {provenance['wall_s']:.0f} s); weights: {out / WEIGHTS}, "
        f"curve: {out / 'curve.png'}"
    )


@app.command(
    epilog=(
        "Examples:\n\n"
        "  gloam segment ../shared/data/real_kitti16 --out results/segment --preview\n\n"
        "  gloam segment data/sim --sequence 00 --frames 10 --weights runs/net/net.npz"
    ),
)
@user_errors
def segment(
    data: DataArg,
    sequence: SequenceOpt = None,
    topic: TopicOpt = None,
    start: StartOpt = 0,
    frames: Annotated[int | None, typer.Option(min=1, help="At most N scans.")] = None,
    stride: StrideOpt = 1,
    out: Annotated[Path, typer.Option(help="Folder for labels/, preview/, segment.json.")] = Path(
        "results/segment"
    ),
    weights: Annotated[
        str, typer.Option(help="Shipped network (default, no-intensity, intensity-rank) or a file.")
    ] = "default",
    preview: Annotated[
        bool, typer.Option(help="Also a bird's-eye PNG per scan, coloured by class.")
    ] = False,
) -> None:
    """Label every point with the net backbone's classes: SemanticKITTI ``.label`` files per
    scan (class id in the low 16 bits) and the share of points per class in segment.json;
    where the data has labels (a KITTI root's labels/), also per-class IoU and mIoU."""
    import numpy as np

    from gloam_jax.datasets import open_dataset
    from gloam_jax.features import NetBackbone
    from gloam_jax.features.net import CLASSES, class_index
    from gloam_jax.io import write_labels
    from gloam_jax.pipeline import select_frames
    from gloam_jax.simulate.preview import render_scan_classes
    from gloam_jax.simulate.world import CLASS_NAMES
    from gloam_jax.training.segmentation import confusion_matrix, iou_scores

    dataset = open_dataset(data, sequence, topic=topic)
    chosen = select_frames(len(dataset), start, frames, stride)
    dataset.check(chosen)
    backbone = NetBackbone(weights)
    counts: dict[int, int] = {}
    confusion, labelled = np.zeros((len(CLASSES), len(CLASSES)), np.int64), 0
    with frame_progress(f"segment {dataset.name}", len(chosen)) as step:
        for k, i in enumerate(chosen):
            t0 = time.perf_counter()
            path = dataset.scan_path(i)
            scan, _ = dataset.frame(i)
            labels = backbone.segment(scan, path)
            write_labels(out / "labels" / f"{path.stem}.label", labels)
            if preview:
                (out / "preview").mkdir(parents=True, exist_ok=True)
                title = f"{path.name}: {len(scan)} points, classes of the net ({weights})"
                render_scan_classes(scan, labels, out / "preview" / f"{path.stem}.png", title)
            truth = dataset.labels(i)
            if truth is not None:
                confusion += confusion_matrix(truth, class_index(labels))
                labelled += 1
            for c, n in zip(*np.unique(labels, return_counts=True), strict=True):
                counts[int(c)] = counts.get(int(c), 0) + int(n)
            step(k, 1e3 * (time.perf_counter() - t0))
    total = sum(counts.values())
    shares = {CLASS_NAMES[k]: n / total for k, n in sorted(counts.items(), key=lambda x: -x[1])}
    summary = {
        "data": str(data), "sequence": dataset.name, "frames": list(chosen), "points": total,
        "weights": weights, "net_data": backbone.provenance.get("data"), "share": shares,
    }  # fmt: skip
    if labelled:
        summary["scores"] = {**iou_scores(confusion), "scans": labelled}
    write_json(out / "segment.json", summary)
    for name, share in shares.items():
        iou = summary.get("scores", {}).get("iou", {}).get(name)
        scored = "" if iou is None else f", IoU {100 * iou:5.1f} %"
        console.print(f"  {name:16s} {100 * share:5.1f} % of points{scored}")
    if labelled:
        miou = summary["scores"]["miou"]
        console.print(f"mIoU {100 * miou:.1f} % over {labelled} labelled scans")
    console.print(f"{len(chosen)} scans, {total} points; labels and summary: {out}")
