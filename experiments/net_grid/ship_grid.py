"""Rewrite the shipped gloam_net model with its network on the registration's grid (the
shipped configs' 0.5 m voxels over 3-100 m, their 10-NN shared): weights, PCA and MLPs
unchanged, the backbone's ``grid`` option and a provenance note added.

    python experiments/net_grid/ship_grid.py COMMIT
"""

import dataclasses
import sys

from gloam_jax.models import load_model, save_model, shipped_model_path

GRID = {"resolution": 0.5, "min_range": 3.0, "max_range": 100.0, "k": 10}

path = shipped_model_path("net")
model = load_model(path)
if "grid" in model.backbone_options:
    sys.exit(f"{path} already runs its network on the grid")
note = {
    "since": sys.argv[1],
    "experiment": "experiments/net_grid",
    "what": "the network runs on the registration's voxels and 10-NN; weights unchanged",
}
model = dataclasses.replace(
    model,
    backbone_options={**model.backbone_options, "grid": GRID},
    provenance={**model.provenance, "backbone_grid": note},
)
save_model(path, model)
print(f"wrote {path}: backbone options {load_model(path).backbone_options}")
