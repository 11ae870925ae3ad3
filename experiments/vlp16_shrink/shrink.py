"""A model's MLPs moved part of the way back to plain GICP.

    python experiments/vlp16_shrink/shrink.py gloam_jax/data/gloam_default.npz 0.5 \\
        runs/vlp16_shrink/a050.npz

With factor a, each MLP's output layer becomes a times its own plus (1 - a) times plain
GICP's constant start (``models.init_model(init="gicp")``): the eigenvalue MLP's raw output is
a * MLP(f) + (1 - a) * plane_output(eps), the conversion MLP's a * MLP(f). a = 1 is the model
itself; a = 0 registers as plain GICP bit for bit (``learned.without_gicp_constants``). On the
VLP-16 model's raw outputs (about 0.9-1.0 for the in-plane values, as GICP's 1) the median
plane thickness scales about linearly with a. Everything else of the file (PCA, backbone,
sensors) is kept; the provenance records the source file, its sha1 and a.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

from gloam_jax.learned import plane_output
from gloam_jax.models import load_model, save_model, with_mlps


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("factor", type=float, help="a in [0, 1]: 1 keeps the model")
    parser.add_argument("out", type=Path)
    args = parser.parse_args(argv)
    a = args.factor
    if not 0.0 <= a <= 1.0:
        sys.exit(f"{args.out}: factor must be in [0, 1], got {a}")
    model = load_model(args.model)
    eig, conv = model.eigenvalue, model.conversion
    eig = eig._replace(w2=a * eig.w2, b2=a * eig.b2 + (1.0 - a) * plane_output(model.eps))
    conv = conv._replace(w2=a * conv.w2, b2=a * conv.b2)
    sha1 = hashlib.sha1(args.model.read_bytes()).hexdigest()
    provenance = {
        **model.provenance,
        "shrunk_to_gicp": {"source": str(args.model), "source_sha1": sha1, "factor": a},
    }
    provenance.pop("test_scores", None)  # the source's test scores are not this file's
    save_model(args.out, with_mlps(model, conv, eig, provenance))
    print(f"{args.out}: {args.model} shrunk to GICP by a = {a:g}")


if __name__ == "__main__":
    main()
