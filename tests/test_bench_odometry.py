"""scripts/bench_odometry.py: how a drive is scored, short or devkit-long."""

import numpy as np
import pytest
from repo_scripts import import_script


@pytest.fixture(scope="module")
def bench_odometry():
    return import_script("bench_odometry")


def _straight(n: int, step_m: float) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 2, 3] = step_m * np.arange(n)  # camera frame: forward is z
    return poses


@pytest.mark.parametrize("n, step_m", [(200, 0.1), (150, 1.0)])
def test_a_drive_is_scored_by_the_devkit_or_over_segments_scaled_to_it(bench_odometry, n, step_m):
    gt = _straight(n, step_m)
    est = _straight(n, 1.01 * step_m)  # 1 % too long everywhere
    scored = bench_odometry.score(gt, est)
    # A segment ends at the first frame past its length: up to one step long, over >= 2 m.
    assert scored["t_err_percent"] == pytest.approx(1.0, abs=0.06)
    assert scored["r_err_deg_per_100m"] == pytest.approx(0.0, abs=1e-6)
    if n * step_m < 100:  # 19.9 m: shorter than the devkit's 100 m, so 10-80 % of the path
        assert scored["lengths_m"] == [2, 4, 6, 8, 10, 12, 14, 16]
    else:
        assert "lengths_m" not in scored
