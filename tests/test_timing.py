"""Stage timings: a frame's stages add up, ``other`` is the rest of its registration, and the
run's summary is each stage's median and 95th percentile."""

import time

import numpy as np
import pytest

from gloam_jax.timing import STAGES, StageTimer, summarise


def test_a_timer_adds_up_each_stage_and_starts_the_next_frame_from_zero():
    timer = StageTimer()
    with timer("load"):
        time.sleep(0.01)
    timer.begin()  # the registration starts: loading lies outside it
    for _ in range(2):  # a stage met twice (two rounds) counts both
        with timer("solve"):
            time.sleep(0.01)
    with pytest.raises(ValueError), timer("map"):  # a block that raises still counts
        time.sleep(0.01)
        raise ValueError
    ms = timer.take(total_ms=100.0)
    assert tuple(ms) == STAGES
    assert 10 <= ms["load"] < 60 and 20 <= ms["solve"] < 100 and 10 <= ms["map"] < 60
    assert ms["voxels"] == ms["features"] == 0
    # other: the registration's time (100 ms) outside its stages (solve, map), load apart
    assert ms["other"] == pytest.approx(100.0 - ms["solve"] - ms["map"], abs=0.02)
    assert set(timer.take().values()) == {0.0}  # the next frame starts from zero


def test_another_threads_stages_count_apart_from_the_registrations_other():
    timer = StageTimer()
    timer.add({"load": 5.0, "voxels": 20.0})  # the prefetch thread's, for this frame
    timer.begin()
    with timer("solve"):
        time.sleep(0.01)
    timer.add({"voxels": 1.0})
    ms = timer.take(total_ms=50.0)
    assert ms["load"] == 5.0 and ms["voxels"] == 21.0
    assert ms["other"] == pytest.approx(50.0 - ms["solve"], abs=0.02)


def test_other_is_never_negative():
    timer = StageTimer()
    with timer("solve"):
        time.sleep(0.005)
    assert timer.take(total_ms=1.0)["other"] == 0.0


def test_the_summary_is_each_stages_median_and_p95_over_the_frames_that_have_one():
    rows = [dict.fromkeys(STAGES, 0.0) | {"solve": float(v), "load": 1.0} for v in range(1, 21)]
    summary = summarise([*rows, {}])  # {}: a frame of an older run, without times
    assert tuple(summary) == STAGES
    assert summary["solve"] == {"median": 10.5, "p95": float(np.percentile(range(1, 21), 95))}
    assert summary["load"] == {"median": 1.0, "p95": 1.0}
    assert summarise([{}, {}]) == {}
