"""t_err per world of the radix-sort commit's val_long runs against the same worlds' runs with
the earlier sort (bitwise the same odometry as cKDTree's): experiments/fast_features' runs for
401/403/404, experiments/map_voxels' base runs for 402/405; draw 0.

    python experiments/voxel_sort/compare.py results/radix_val results/fast_features \
        results/map_voxels_base
"""

import glob
import json
import sys


def cells(root: str, gloam: str | None) -> dict[tuple[str, str], float]:
    """(GICP or GLOAM, world) -> t_err (%) of draw 0's runs under root."""
    out = {}
    for f in glob.glob(f"{root}/**/long-9d28df01/*/metrics.json", recursive=True):
        label = "GICP" if "/GICP/" in f else "GLOAM" if gloam is None or gloam in f else None
        if label:
            out[(label, f.split("/")[-2])] = json.load(open(f))["t_err_percent"]
    return out


new = cells(sys.argv[1], None)
old = cells(sys.argv[2], "GLOAM (hdl64)") | cells(sys.argv[3], "GLOAM (d)")
for key in sorted(new):
    print(*key, f"{old[key]:.5f} -> {new[key]:.5f}  ratio {new[key] / old[key]:.4f}")
