"""Write docs/config.md: every setting of the odometry and training files, with its type,
default, unit and meaning, read from the settings dataclasses and their field comments
(gloam_jax.cli.config.setting_rows), so the page cannot drift from the code.

    python scripts/config_docs.py                     # print the page
    python scripts/config_docs.py --write docs/config.md
    python scripts/config_docs.py --check docs/config.md   # exit 1 when stale (a test runs it)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from gloam_jax.cli.config import setting_rows
from gloam_jax.odometry import OdometryConfig
from gloam_jax.training.config import TrainConfig

INTRO = """# Settings

Every setting of the odometry files (`gloam run --config`, `configs/gicp.yaml` ...) and the
training files (`gloam train --config`, `configs/train_*.yaml`), generated from the settings
dataclasses and the comments on their fields by `python scripts/config_docs.py --write
docs/config.md` (a test fails when this page is stale). Nested sections are written
`section.field` here and as nested mappings in YAML; a section left out keeps its defaults.
`gloam config dump METHOD` writes one method's settings as commented YAML. A setting without
a comment in the source has an empty meaning here: add one on its line.

A file can start from another and state only what it changes: `base: gicp` (a shipped
config's name) or `base: mine.yaml` (a path relative to the file) is loaded first, and the
file's settings replace its values section by section (`configs/gloam.yaml` is `base: gicp`
plus the method, the model and 5 candidates). The `config.yaml` that `gloam run` and `gloam
train` write in their run folders holds the resolved whole.

Bad values are errors naming the file and the setting (a range band that keeps no point,
a negative voxel size, fewer than 3 neighbours, ...). `preprocess.downsampling_resolution: 0`
turns downsampling off; `preprocess.min_range: 0` keeps the closest returns.

**Deskew** (`preprocess.deskew`): `auto` uses per-point times when the scans carry them
(`timestamps/NNNNNN.npy` in the KITTI layout, a `t`/`time`/`timestamp` field in PCD or PLY
scans), the azimuth for the KITTI layout without them (taken as motion-distorted, as the
simulator writes it), and nothing otherwise; the run summary and `metrics.json` (`deskew`) say
which was used and why. KITTI odometry's own readme, as quoted in public issue threads, says
its Velodyne scans were already egomotion-compensated, and 16 real KITTI scans fit the map no
worse without deskew ([experiments/undistorted_scans](../experiments/undistorted_scans/README.md)):
for the real benchmark's scans `deskew: off` may be right (unmeasured: no ground truth here).
Choosing by that fit automatically was tried and failed on the test worlds (same experiment).
Per-point times may be seconds from the sweep's start, from mid-sweep or before its end, a
[0, 1] fraction, or absolute seconds / nanoseconds (also ms, us): like KISS-ICP, they are
mapped by their span onto one sweep of `preprocess.sweep_duration`, and the convention found
is recorded (`deskew.time_convention`). A span that fits none is an error.

**Model and guard** (`model`, `guard`): every model file records the sensors it was trained
for (rings, vertical field of view, points per scan; `gloam model-info` lists them: the shipped
models know the HDL-64E and the VLP-16). `model: default` measures the run's first three scans
and runs the first shipped model trained for their sensor; where none is (an OS1-64, an
HDL-32E), or more than 10 % of their points lie outside the model's feature region, `guard`
runs instead: plain GICP (`gicp`), the model's learned association alone (`gicp_da`), or the
model all the same (`off`). A model named otherwise (`--weights FILE`, `model: net`, a path)
runs whatever the sensor, with a warning; an older file without the record too. The run
summary and `metrics.json` (`model_choice`: model, method, sensor, decision, reason) say which
model ran and why ([experiments/sensor_guard](../experiments/sensor_guard/README.md)).
"""

SECTIONS = (
    ("Odometry (`OdometryConfig`)", OdometryConfig),
    ("Training (`TrainConfig`)", TrainConfig),
)


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def render() -> str:
    parts = [INTRO]
    for title, cls in SECTIONS:
        parts.append(f"\n## {title}\n\n| setting | type | default | unit | meaning |\n")
        parts.append("|---|---|---|---|---|\n")
        for row in setting_rows(cls):
            cells = [f"`{row['name']}`", f"`{row['type']}`", f"`{row['default']}`",
                     row["unit"], row["meaning"]]  # fmt: skip
            parts.append("| " + " | ".join(_cell(c) for c in cells) + " |\n")
        for key, why in getattr(cls, "RETIRED", {}).items():
            parts.append(f"\nRetired: `{key}` is accepted in old files and ignored ({why}).\n")
    return "".join(parts)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--write", type=Path, help="write the page here")
    group.add_argument("--check", type=Path, help="exit 1 if this page differs")
    args = parser.parse_args()
    page = render()
    if args.write:
        args.write.write_text(page)
    elif args.check:
        if not args.check.exists() or args.check.read_text() != page:
            print(f"{args.check} is stale: python scripts/config_docs.py --write {args.check}")
            return 1
    else:
        sys.stdout.write(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
