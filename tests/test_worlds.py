"""Worlds that differ (issue 18): world specs drawn from a seed, the sensor models and their
error parameters, the forest and yard families, and the train/validation/test split."""

import json
from dataclasses import replace

import numpy as np
import pytest
from shared_data import shared_path
from test_simulate import flat_scene, straight_trajectory, world_points
from typer.testing import CliRunner

from gloam_jax.cli import app
from gloam_jax.errors import InputError
from gloam_jax.simulate import (
    ErrorSwitches,
    SweepSimulator,
    build_scene,
    draw_world,
    get_sensor,
    load_world,
    simulate,
)
from gloam_jax.simulate.spec import SENSOR_RANGES, SensorSpec
from gloam_jax.simulate.styles import RANGES
from gloam_jax.simulate.world import (
    BUILDING,
    CAR,
    FENCE,
    OTHER_STRUCTURE,
    PARKING,
    POLE,
    ROAD,
    SIDEWALK,
    TERRAIN,
    TRUNK,
    VEGETATION,
)
from gloam_jax.training.protocol import (
    HELD_OUT_FAMILY,
    HELD_OUT_SENSOR,
    LONG_FRAMES,
    LONG_METRES,
    SPLITS,
    TEST_SEQUENCES,
    TRAIN_SEQUENCES,
    world_spec,
)

SENSOR_ONLY = ErrorSwitches(False, False, False, True)


def test_a_world_is_drawn_from_its_seed_within_the_ranges():
    kw = dict(family="forest", sensor="vlp16", frames=2)
    world = draw_world(11, **kw)
    assert draw_world(11, **kw) == world and draw_world(12, **kw) != world
    for family, ranges in RANGES.items():
        for seed in range(5):
            w = draw_world(seed, family=family, sensor="os1-64")
            for name, (lo, hi) in ranges.items():
                value = getattr(w.scene, name)
                for v in value if isinstance(value, tuple) else (value,):
                    assert lo <= v <= hi, (family, name)
            for name in ("range_noise", "elevation_bias_deg", "beam_jitter_deg", "dropout"):
                lo, hi = SENSOR_RANGES["os1-64"][name]
                assert lo <= getattr(w.sensor, name) <= hi
    assert {draw_world(s, **kw).motion_distortion for s in range(20)} == {True, False}


def test_sensor_models_have_their_beams_and_columns():
    hdl, vlp, os1 = get_sensor("hdl64"), get_sensor("vlp16"), get_sensor("os1-64")
    assert (hdl.num_beams, vlp.num_beams, os1.num_beams) == (64, 16, 64)
    np.testing.assert_allclose(vlp.elevations_deg, np.arange(15, -16, -2))
    # OS1-64: uniform spacing over +-16.6 deg; HDL-64: two blocks, the lower one coarser.
    np.testing.assert_allclose(np.diff(os1.elevations_deg), -33.2 / 63)
    assert os1.elevations_deg[0] == pytest.approx(16.6) and os1.num_columns == 1024
    steps = -np.diff(hdl.elevations_deg)
    assert steps[:31].max() < 0.34 < 0.5 < steps[32:].min()
    # HDL-32E (training only): 32 beams 1.33 deg apart, between the HDL-64's and the VLP-16's.
    hdl32 = get_sensor("hdl32")
    assert hdl32.num_beams == 32 and hdl32.num_columns == 2200
    np.testing.assert_allclose(np.diff(hdl32.elevations_deg), -41.34 / 31)
    assert draw_world(0, family="urban", sensor="hdl32").sensor.name == "hdl32"
    assert {SensorSpec("os1-64", c, 0.02, 0.0, 0.0, 0.0).model().num_columns
            for c in SENSOR_RANGES["os1-64"]["num_columns"]} == {1024, 2048}  # fmt: skip
    drawn = {draw_world(s, family="yard", sensor="os1-64").sensor.num_columns for s in range(12)}
    assert drawn == {1024, 2048}
    spec = SensorSpec("vlp16", 900, range_noise=0.035, elevation_bias_deg=-0.1,
                      beam_jitter_deg=0.02, dropout=0.04)  # fmt: skip
    model = spec.model(num_beams=8)
    assert (model.num_columns, model.num_beams, model.range_noise, model.dropout) == (
        900, 8, 0.035, 0.04)  # fmt: skip
    assert (model.elevation_bias_deg, model.beam_jitter_deg) == (-0.1, 0.02)


def _scan(sensor, boxes=()):
    traj = straight_trajectory(speed=0.0)
    sim = SweepSimulator(flat_scene(boxes), traj, sensor, seed=0, switches=SENSOR_ONLY)
    scan = sim.frame(0)
    return scan, world_points(scan, traj.frame_poses[0])


def test_dropout_jitter_and_range_noise_change_what_they_should():
    clean = get_sensor("vlp16", num_columns=400).without_errors()
    wall = ([10.0, 0.0, 5.0], [0.5, 30.0, 5.0])
    base, p0 = _scan(clean, [wall])
    np.testing.assert_allclose(p0[base.labels == TERRAIN, 2], 0.0, atol=2e-3)
    # Dropout removes that fraction of the returns, and nothing else moves.
    # (any dropout also loses returns too weak to detect: compare with a negligible one)
    few, _ = _scan(replace(clean, dropout=1e-9), [wall])
    dropped, p1 = _scan(replace(clean, dropout=0.3), [wall])
    assert len(dropped.points) / len(few.points) == pytest.approx(0.7, abs=0.03)
    np.testing.assert_allclose(p1[dropped.labels == BUILDING, 0], 9.5, atol=2e-3)
    # Beam jitter: rays leave off their nominal elevation, so flat ground is reported at
    # heights of about range * jitter; the points are as many as before.
    jittered, p2 = _scan(replace(clean, beam_jitter_deg=0.1), [wall])
    ground = jittered.labels == TERRAIN
    r = np.linalg.norm(jittered.points[ground, :3], axis=1)
    assert np.std(p2[ground, 2] / r) == pytest.approx(np.deg2rad(0.1), rel=0.25)
    assert len(jittered.points) == pytest.approx(len(base.points), rel=0.05)
    # Range noise: the wall's points scatter along the rays by the configured sigma.
    noisy, p3 = _scan(replace(clean, range_noise=0.04), [wall])
    front = (noisy.labels == BUILDING) & (np.abs(p3[:, 1]) < 3)
    resid = (p3[front, 0] - 9.5) * np.linalg.norm(noisy.points[front, :3], axis=1) / 9.5
    assert np.std(resid) == pytest.approx(0.04, rel=0.25)


def _small_world(family):
    """A drawn world at the recorded speed: both families share the drive (and the
    compilations of its interpolation)."""
    world = draw_world(1, family=family, sensor="hdl64", frames=2, motion_distortion=False)
    return replace(world, speed_scale=1.0)


@pytest.mark.parametrize(
    ("family", "must", "must_not"),
    [
        ("forest", {ROAD, TERRAIN, VEGETATION, TRUNK}, {SIDEWALK, PARKING}),
        ("yard", {ROAD, PARKING, CAR, OTHER_STRUCTURE, POLE, FENCE, BUILDING}, {SIDEWALK}),
    ],
)
def test_new_families_produce_their_classes_and_record_their_world(
    tmp_path, family, must, must_not
):
    world = _small_world(family)
    kw = dict(world=world, num_beams=16, num_columns=360, sequence="7")
    seq_dir = simulate(tmp_path, **kw)
    labels = np.fromfile(seq_dir / "labels/000001.label", np.uint32) & 0xFFFF
    classes = set(np.unique(labels).tolist())
    assert must <= classes and not must_not & classes, sorted(classes)
    if family == "forest":  # woods, hardly anything built
        assert np.isin(labels, [VEGETATION, TRUNK]).mean() > 10 * (labels == BUILDING).mean()
    # The world is recorded beside the scans and reads back equal.
    record = json.loads((seq_dir / "world.json").read_text())
    assert load_world(seq_dir / "world.json") == world and record["family"] == family
    assert record["drive"]["length_m"] > 0
    assert json.loads((seq_dir / "simulation.json").read_text())["config"]["world"]["seed"] == 1
    (tmp_path / "w.yaml").write_text(json.dumps(world.to_dict()))  # JSON is YAML too
    assert load_world(tmp_path / "w.yaml") == world
    # Finished: a rerun returns at once; another world in the same folder is refused.
    assert simulate(tmp_path, **kw) == seq_dir
    with pytest.raises(InputError, match="different simulation"):
        simulate(tmp_path, **{**kw, "world": draw_world(2, family=family, sensor="hdl64")})


def test_street_styles_keep_their_scenes():
    traj = straight_trajectory(frames=3)
    scene = build_scene(traj, "urban", seed=2)
    assert scene.ground.labels == (ROAD, SIDEWALK, TERRAIN)
    assert BUILDING in scene.boxes.label and PARKING not in scene.boxes.label


def test_splits_leave_one_family_and_one_sensor_to_test():
    worlds = [w for split in SPLITS.values() for w in split]
    assert len({w.sequence for w in worlds}) == len(worlds)
    seen = {s: {(w.family, w.sensor) for w in SPLITS[s]} for s in SPLITS}
    for split in ("train", "val", "val_long"):
        assert HELD_OUT_FAMILY not in {f for f, _ in seen[split]}
        assert HELD_OUT_SENSOR not in {s for _, s in seen[split]}
        assert {w.trajectory for w in SPLITS[split]} <= set(TRAIN_SEQUENCES)
    for test in (SPLITS["test"], SPLITS["test_long"]):
        assert {w.trajectory for w in test} <= set(TEST_SEQUENCES)
        assert HELD_OUT_FAMILY in {w.family for w in test}
        assert HELD_OUT_SENSOR in {w.sensor for w in test}
        assert any(not w.motion_distortion for w in test)
        # Held out alone and together; every training family and sensor is tested too.
        assert {(w.family == HELD_OUT_FAMILY, w.sensor == HELD_OUT_SENSOR) for w in test} == {
            (True, True), (True, False), (False, True), (False, False)}  # fmt: skip
        assert {f for f, _ in seen["train"]} <= {w.family for w in test}
    # Short validation windows share no pose with a training window of the same trajectory.
    short = [w for split in ("train", "val", "test") for w in SPLITS[split]]
    longest = max(int(np.ceil(w.frames * w.speed_scale)) + 2
                  for w in map(world_spec, short))  # fmt: skip
    for v in SPLITS["val"]:
        for t in SPLITS["train"]:
            assert v.trajectory != t.trajectory or abs(v.start - t.start) > longest
    test = SPLITS["test"]
    assert world_spec(test[0]) == world_spec(test[0]) != world_spec(test[0], seed_offset=1)


def test_long_worlds_drive_kitti_lengths_and_stop_where_their_trajectory_does():
    """At least 1000 frames and 500 m, or to the trajectory's end at the drawn speed; long
    test worlds on one trajectory share no pose at any drawn speed."""
    from gloam_jax.io import read_kitti_poses
    from gloam_jax.metrics import path_lengths

    poses, spans = {}, {}
    for world in SPLITS["val_long"] + SPLITS["test_long"]:
        if world.trajectory not in poses:
            path = shared_path(f"kitti_gt_poses/{world.trajectory}.txt")
            poses[world.trajectory] = read_kitti_poses(path)
        P = poses[world.trajectory]
        for offset in (0, 1, 2):  # three simulation draws, three speeds
            spec = world_spec(world, seed_offset=offset, positions=P[:, :3, 3])
            last = world.start + (spec.frames - 1) * spec.speed_scale  # a pose index
            driven = path_lengths(P[world.start : int(last) + 1])[-1]
            assert last <= len(P) - 2
            ended = last > len(P) - 3 - spec.speed_scale  # stopped by the trajectory's end
            assert ended or (spec.frames >= LONG_FRAMES and driven >= LONG_METRES), world
        span = (world.start, world.start + spec.frames * 1.35)  # the fastest drawn speed
        if world in SPLITS["test_long"]:
            for other in spans.get(world.trajectory, []):
                assert span[1] < other[0] or other[1] < span[0], world.sequence
            spans.setdefault(world.trajectory, []).append(span)
    # KITTI 04 and 03 are shorter than 500 m: driven to their ends
    assert {w.trajectory for w in SPLITS["val_long"] + SPLITS["test_long"]} >= {"03", "04"}
    with pytest.raises(ValueError, match="no frames fit"):
        world_spec(SPLITS["test_long"][0], positions=np.zeros((2, 3)))


def _write(path, data):
    path.write_text(json.dumps(data))
    return path


def test_bad_world_input_is_one_line_naming_the_file(tmp_path):
    good = draw_world(3, family="yard", sensor="vlp16").to_dict()
    cases = [
        ({**good, "family": "desert"}, "unknown scene family 'desert'"),
        ({**good, "sensor": {**good["sensor"], "dropout": -0.1}}, "sensor.dropout must be"),
        ({**good, "sensor": {**good["sensor"], "name": "hdl128"}}, "unknown sensor 'hdl128'"),
        ({**good, "scene": {**good["scene"], "building_height": [9, 3]}}, "building_height"),
        ({**good, "scene": {**good["scene"], "tree_spacing": 0}}, "scene.tree_spacing must"),
        ({k: v for k, v in good.items() if k != "frames"}, "world lacks frames"),
        ({**good, "speed": 2}, "unknown world setting 'speed'"),
        ({**good, "speed_scale": 9}, "speed_scale must be a number from 0.25 to 4"),
        ({**good, "trajectory": "kitti"}, "trajectory must be a KITTI sequence id"),
        ([1, 2], "a world must be a mapping"),
    ]
    for data, message in cases:
        path = _write(tmp_path / "world.json", data)
        with pytest.raises(InputError, match=message) as err:
            load_world(path)
        assert str(err.value).startswith(str(path)) and "\n" not in str(err.value)
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(InputError, match="broken.json: not valid JSON"):
        load_world(tmp_path / "broken.json")
    world = draw_world(3, family="yard", sensor="vlp16", trajectory="07")
    with pytest.raises(InputError, match="the world sets style, seed"):
        simulate(tmp_path / "x", world=world, style="urban", seed=1)
    with pytest.raises(InputError, match="the world drives along 07.txt"):
        simulate(tmp_path / "x", world=world)


def test_gloam_simulate_replays_a_world_file(tmp_path):
    world = _small_world("yard")  # the family test's: its compilations are reused
    path = _write(tmp_path / "world.json", world.to_dict())
    runner = CliRunner()
    args = ["simulate", str(tmp_path / "out"), "--world", str(path), "--beams", "16",
            "--columns", "360", "--sequence", "05"]  # fmt: skip
    bad = runner.invoke(app, [*args, "--style", "urban"])
    assert bad.exit_code == 2 and "the world sets style" in bad.output
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert load_world(tmp_path / "out/sequences/05/world.json") == world
