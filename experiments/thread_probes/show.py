"""One line of a bench_odometry --out file: frame median / p95 and the median stages.

python experiments/thread_probes/show.py OUT.json LABEL
"""

import json
import sys

d = json.load(open(sys.argv[1]))


def find(o):
    if isinstance(o, dict):
        if "stage_ms" in o:
            return o
        for v in o.values():
            x = find(v)
            if x:
                return x


m = find(d)
print(
    sys.argv[2],
    "frame {:.1f} p95 {:.1f}".format(m["frame_ms"]["median"], m["frame_ms"]["p95"]),
    {k: round(v["median"], 1) for k, v in m["stage_ms"].items()},
)
