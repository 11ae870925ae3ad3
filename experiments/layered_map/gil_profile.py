"""Where a frame's threads hold Python's GIL: py-spy samples (``--gil``: only the thread
holding it) of 300 `gicp` frames of val 403 d0 (the change), summed per innermost
gloam_jax function over the frame loop and its threads, in ms per frame (compiling frames
included).

    py-spy record --gil --threads -r 250 --format raw -o gil_gicp.txt -- \
        python experiments/layered_map/poses.py data/long 403 300 gicp /tmp/poses.npy
    python experiments/layered_map/gil_profile.py gil_gicp.txt > gil_profile.txt
"""

import collections
import re
import sys

RATE, FRAMES = 250, 300
held = collections.Counter()
with open(sys.argv[1]) as samples:
    for line in samples:
        stack, count = line.rsplit(" ", 1)
        if not any(s in stack for s in ("run_ours", "prefetch", "local-map")):
            continue  # start-up, imports, scoring
        frames = stack.split(";")
        ours = [f for f in frames if "/gloam_jax/" in f]
        thread = frames[0].split(":")[-1].strip()
        where = re.sub(r" \(.*/gloam_jax/", " (", ours[-1]) if ours else frames[-1]
        held[(thread, where)] += int(count)
ms = 1e3 / RATE / FRAMES
print(f"GIL held, ms per frame, all threads of the frame loop: {sum(held.values()) * ms:.1f}")
for (thread, where), count in held.most_common(15):
    print(f"{count * ms:5.2f}  {thread:12s} {where}")
