"""bench_odometry.py with Python's GIL switch interval set first (default 0.005 s):

    python experiments/thread_probes/switch_interval.py 0.0005 data/long --sequences 403 \\
        --frames 300 --methods gicp --out OUT.json
"""

import runpy
import sys

sys.setswitchinterval(float(sys.argv.pop(1)))
sys.argv[0] = "scripts/bench_odometry.py"
sys.path.insert(0, "scripts")
runpy.run_path("scripts/bench_odometry.py", run_name="__main__")
