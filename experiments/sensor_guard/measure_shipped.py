"""Record the training sensors in the shipped model files (issue 41, item 3), once.

For every protocol world a shipped model was trained on (provenance config.sequences, the
worlds of training.protocol.SPLITS), simulate its first frames at full resolution, measure
the signature (gloam_jax.sensor.measure), merge per sensor, and save the shipped file with
the record, its arrays unchanged (checked). Also measures the real KITTI scans and the
held-out OS1-64 test worlds against the records. Writes shipped_sensors.json beside itself.

    PYTHONPATH=. python experiments/sensor_guard/measure_shipped.py [--dry-run]
"""

from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from gloam_jax.io import read_scan
from gloam_jax.models import SHIPPED_MODELS, load_model, save_model, shipped_model_path
from gloam_jax.sensor import SENSOR_SCANS, first_match, measure, merge
from gloam_jax.simulate import simulate
from gloam_jax.training.protocol import SPLITS, world_spec

HERE = Path(__file__).resolve().parent
SHARED = HERE.parents[2] / "shared" / "data"
WORLDS = {w.sequence: w for split in SPLITS.values() for w in split}


def world_signature(sequence: str):
    """The signature of a protocol world's first SENSOR_SCANS frames, named by its sensor."""
    world = WORLDS[sequence]
    spec = world_spec(world, frames=SENSOR_SCANS)
    poses = SHARED / "kitti_gt_poses" / f"{world.trajectory}.txt"
    with tempfile.TemporaryDirectory() as tmp:
        seq = simulate(tmp, world=spec, trajectory=poses, sequence=sequence)
        scans = [read_scan(p) for p in sorted((seq / "velodyne").glob("*.bin"))]
        return measure(scans, name=world.sensor)


def same_arrays(a: Path, b: Path) -> bool:
    with np.load(a) as x, np.load(b) as y:
        keys = set(x.files) - {"metadata"}
        if keys != set(y.files) - {"metadata"}:
            return False
        meta_x, meta_y = json.loads(str(x["metadata"])), json.loads(str(y["metadata"]))
        meta_y.pop("sensors", None)
        return meta_x == meta_y and all(
            x[k].dtype == y[k].dtype and np.array_equal(x[k], y[k]) for k in keys
        )


def main(dry_run: bool) -> None:
    out: dict = {"worlds": {}, "models": {}}
    signatures = {}
    for name in SHIPPED_MODELS:
        for seq in load_model(name).provenance["config"]["sequences"]:
            if seq not in signatures:
                signatures[seq] = world_signature(seq)
                out["worlds"][seq] = signatures[seq].to_dict()
                print(seq, signatures[seq].describe(), flush=True)
    for name in SHIPPED_MODELS:
        path = shipped_model_path(name)
        model = load_model(name)
        sensors = tuple(merge([signatures[s] for s in model.provenance["config"]["sequences"]]))
        out["models"][name] = [s.to_dict() for s in sensors]
        print(name, "; ".join(s.describe() for s in sensors))
        if dry_run:
            continue
        before = Path(tempfile.mkdtemp()) / path.name
        before.write_bytes(path.read_bytes())
        save_model(path, dataclasses.replace(model, sensors=sensors))
        assert same_arrays(before, path), f"{path}: arrays or metadata changed"
        assert load_model(name).sensors == sensors
    records = merge(list(signatures.values()))
    real = sorted((SHARED / "real_kitti16").glob("*.bin"))
    checks = {f"real_kitti16 {k:02d}-{k + 2:02d}": [read_scan(p) for p in real[k : k + 3]]
              for k in range(0, 14, 3)}  # fmt: skip
    for seq in ("302", "305", "307"):  # the held-out OS1-64 test worlds
        checks[f"world {seq} (os1-64)"] = world_signature(seq)
    out["checks"] = {}
    for what, scans in checks.items():
        sig = scans if not isinstance(scans, list) else measure(scans)
        found, why = first_match(sig, records)
        out["checks"][what] = {"signature": sig.to_dict(), "match": found and found.name,
                               "reason": why}  # fmt: skip
        print(what, sig.describe(), "->", found and found.name, "|", why)
    (HERE / "shipped_sensors.json").write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main("--dry-run" in sys.argv)
