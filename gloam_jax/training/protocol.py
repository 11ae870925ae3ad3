"""The training and evaluation protocol: the paper's split of KITTI sequences, as simulated
windows of the real ground-truth trajectories.

The paper trains on KITTI 01, 03, 05, 07, 09 and tests on 00, 02, 04, 06, 08, 10. We drive the
simulator along a window of each real trajectory, in a scene style that resembles the
sequence (city blocks, residential streets, the highway of 01 and the country road of 04).
"""

from __future__ import annotations

from typing import NamedTuple

TRAIN_SEQUENCES: tuple[str, ...] = ("01", "03", "05", "07", "09")
TEST_SEQUENCES: tuple[str, ...] = ("00", "02", "04", "06", "08", "10")


class SimWindow(NamedTuple):
    """A simulated window of a KITTI sequence: scene style and first pose index."""

    style: str
    start: int


# Starts are chosen so that 120 frames cover 70-180 m (the car moves in each window).
WINDOWS: dict[str, SimWindow] = {
    "00": SimWindow("urban", 0),
    "01": SimWindow("highway", 0),
    "02": SimWindow("suburban", 0),
    "03": SimWindow("suburban", 300),
    "04": SimWindow("highway", 0),
    "05": SimWindow("suburban", 0),
    "06": SimWindow("suburban", 0),
    "07": SimWindow("urban", 500),
    "08": SimWindow("urban", 100),
    "09": SimWindow("suburban", 0),
    "10": SimWindow("suburban", 100),
}
DEFAULT_FRAMES = 120

# Second training windows of the training sequences, under ids KITTI does not use (3N is a
# second window of 0N): more training data, still only from the training trajectories.
EXTRA_TRAINING_WINDOWS: dict[str, tuple[str, SimWindow]] = {
    "31": ("01", SimWindow("highway", 600)),
    "33": ("03", SimWindow("suburban", 500)),
    "35": ("05", SimWindow("suburban", 1500)),
    "37": ("07", SimWindow("urban", 800)),
    "39": ("09", SimWindow("suburban", 800)),
}
