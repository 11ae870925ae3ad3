"""``gloam train-backbone``: the ``net`` backbone's segmentation network, on labelled scans."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from gloam_jax.cli.common import Tasks, app, console, progress_bar, user_errors


def _ids(text: str) -> tuple[str, ...]:
    return tuple(s.strip() for s in text.split(",") if s.strip())


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
) -> None:
    """Train the segmentation network whose per-point embedding is the ``net`` backbone."""
    from gloam_jax.training.segmentation import WEIGHTS, SegmentationConfig, train_segmentation

    cfg = SegmentationConfig(
        data=str(data), train=_ids(train), test=_ids(test), steps=steps, batch=batch, crop=crop,
        learning_rate=learning_rate, eval_every=eval_every, test_every=test_every, seed=seed,
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
