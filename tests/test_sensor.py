"""The sensor signature (gloam_jax.sensor) and the model choice and guard (gloam_jax.guard):
every preset tells itself from the others, real KITTI scans are an HDL-64E, and a run on a
sensor no shipped model was trained for runs plain GICP and says so."""

import dataclasses
import json

import numpy as np
import pytest
from shared_data import shared_path

from gloam_jax.config import load_config
from gloam_jax.errors import InputError
from gloam_jax.features.novelty import FeatureNovelty
from gloam_jax.guard import choose
from gloam_jax.io import read_scan
from gloam_jax.models import load_model, save_model, shipped_model_path
from gloam_jax.odometry import Odometry, resolve_map_resolution
from gloam_jax.pipeline import run_sequence
from gloam_jax.sensor import SensorSignature, first_match, matches, measure
from gloam_jax.simulate import SENSORS, draw_world, simulate

# One worker runs this module (pytest-xdist --dist loadgroup): its presets (8 simulations)
# are made once, not once per worker.
pytestmark = pytest.mark.xdist_group("sensor")

COLUMNS = 360  # thinned columns (fast: compiling dominates); every preset keeps all its rings


def _scans(root, sensor, family, distortion, frames=2, seed=5):
    world = draw_world(seed, family=family, sensor=sensor, frames=frames,
                       motion_distortion=distortion)  # fmt: skip
    seq = simulate(root, world=world, num_columns=COLUMNS)
    return seq, [read_scan(p) for p in sorted((seq / "velodyne").glob("*.bin"))]


@pytest.fixture(scope="module")
def presets(tmp_path_factory):
    """Per preset: a record measured on an urban world with motion distortion, and the
    signature of a highway world without it (another scene, top rings in the sky)."""
    out = {}
    for name in SENSORS:
        root = tmp_path_factory.mktemp(name)
        _, urban = _scans(root / "urban", name, "urban", True)
        seq, highway = _scans(root / "highway", name, "highway", False)
        out[name] = (measure(urban, name=name), measure(highway), seq.parent.parent)
    return out


@pytest.fixture(scope="module")
def real():
    return [read_scan(p) for p in sorted(shared_path("real_kitti16").glob("*.bin"))]


def test_every_preset_matches_its_own_record_and_no_other(presets):
    for name, (_, measured, _) in presets.items():
        assert measured.rings <= SENSORS[name].num_beams
        for other, (record, _, _) in presets.items():
            ok, why = matches(measured, record)
            assert ok == (name == other), f"{name} scans against {other}'s record: {why}"


def test_real_kitti_scans_match_the_shipped_hdl64_record(real):
    records = load_model("default").sensors
    assert {s.name for s in records} == {"hdl64", "vlp16"}
    for k in (0, 6, 13):
        found, why = first_match(measure(real[k : k + 3]), records)
        assert found is not None and found.name == "hdl64", why


def test_signature_round_trip_and_malformed_records():
    s = SensorSignature(64, -24.8, 2.0, 121000, "hdl64")
    assert SensorSignature.from_dict(json.loads(json.dumps(s.to_dict()))) == s
    assert "name" not in dataclasses.replace(s, name=None).to_dict()
    for bad in ([64], {"rings": 64}, {**s.to_dict(), "rings": 6.5},
                {**s.to_dict(), "low_deg": 5.0}, {**s.to_dict(), "colour": 1}):  # fmt: skip
        with pytest.raises(InputError) as e:
            SensorSignature.from_dict(bad)
        assert "\n" not in str(e.value)
    with pytest.raises(InputError, match="too few"):
        measure([np.zeros((10, 4), np.float32)])


def test_model_file_round_trips_its_sensors_and_names_a_malformed_one(tmp_path):
    model = load_model("default")
    assert model.sensors is not None
    path = tmp_path / "m.npz"
    save_model(path, model)
    assert load_model(path).sensors == model.sensors
    save_model(path, dataclasses.replace(model, sensors=None))  # an older file: no record
    assert load_model(path).sensors is None
    bad = dataclasses.replace(model, sensors=(dataclasses.replace(model.sensors[0], rings=0),))
    save_model(path, bad)
    with pytest.raises(InputError) as e:
        load_model(path)
    assert str(e.value).startswith(f"{path}: metadata 'sensors'") and "\n" not in str(e.value)


def _stub_features(model, k):
    return np.zeros((1000, model.pca.input_dim))


def test_default_picks_the_shipped_hdl64_model_for_real_kitti_scans(real):
    choice = choose(load_config("gloam"), real[:3], _stub_features)
    assert choice.record["decision"] == "model" and choice.record["model"] == "hdl64"
    assert choice.config.method == "gloam" and choice.warning is None
    assert "matches hdl64" in choice.record["reason"]
    assert choice.model.provenance["selected_on"] == "val_long"


@pytest.mark.parametrize(
    ("signature", "picked"),
    [
        (SensorSignature(64, -24.8, 2.0, 120000), "hdl64"),
        (SensorSignature(16, -15.0, 15.0, 19000), "default"),  # VLP-16: the protocol's model
        (SensorSignature(32, -30.7, 10.7, 60000), None),  # HDL-32E: no shipped model, guarded
    ],
)
def test_default_picks_a_model_per_sensor(signature, picked, monkeypatch):
    import gloam_jax.guard as guard

    monkeypatch.setattr(guard, "try_measure", lambda scans: signature)
    choice = choose(load_config("gloam"), [np.zeros((10, 4))], _stub_features)
    assert choice.record["model"] == picked
    assert choice.config.method == ("gloam" if picked else "gicp")


def test_a_run_on_os1_64_scans_runs_the_guard_and_says_so(presets, tmp_path):
    root = presets["os1-64"][2]
    result = run_sequence(root, "00", load_config("gloam"), tmp_path / "run", frames=2)
    written = json.loads((tmp_path / "run" / "metrics.json").read_text())["model_choice"]
    assert written == result["model_choice"]
    assert written["decision"] == "guard: gicp" and written["method"] == "gicp"
    assert written["model"] is None and written["sensor"]["low_deg"] == pytest.approx(-16.6)
    assert "default: not hdl64" in written["reason"]
    # guard: gicp_da keeps the shipped model's association; off runs the model, warning.
    scans = [read_scan(p) for p in sorted((root / "sequences/00/velodyne").glob("*.bin"))]
    da = choose(dataclasses.replace(load_config("gloam"), guard="gicp_da"), scans, _stub_features)
    assert da.config.method == "gicp_da" and da.model is not None and da.warning is None
    off = choose(dataclasses.replace(load_config("gloam"), guard="off"), scans, _stub_features)
    assert off.config.method == "gloam" and "guard: off" in off.warning


def test_a_forced_model_runs_with_a_warning(presets, tmp_path):
    scans = [read_scan(p) for p in sorted((presets["os1-64"][2] / "sequences/00/velodyne").glob(
        "*.bin"))]  # fmt: skip
    forced = dataclasses.replace(load_config("gloam"), model=str(shipped_model_path()))
    choice = choose(forced, scans, _stub_features)
    assert choice.config.method == "gloam" and choice.record["decision"] == "forced"
    assert "forced" in choice.warning and "not hdl64" in choice.warning
    # An older file without a record runs as well, with a warning that says so.
    old = tmp_path / "old.npz"
    save_model(old, dataclasses.replace(load_model("default"), sensors=None))
    choice = choose(dataclasses.replace(forced, model=str(old)), scans, _stub_features)
    assert choice.config.method == "gloam" and "records no training sensors" in choice.warning


def test_features_outside_the_models_region_guard_or_warn(real, tmp_path, monkeypatch):
    model = load_model("default")
    d = model.pca_features(np.zeros((1, model.pca.input_dim))).shape[1]
    tight = FeatureNovelty(np.full(d, 1e3), np.eye(d), 1.0)  # every point lies outside
    path = tmp_path / "novel.npz"
    save_model(path, dataclasses.replace(model, novelty=tight))
    forced = dataclasses.replace(load_config("gloam"), model=str(path))
    choice = choose(forced, real[:3], _stub_features)
    assert choice.record["decision"] == "forced" and choice.record["outside_share"] == 1.0
    assert "outside the model's training features" in choice.warning
    monkeypatch.setattr("gloam_jax.guard.load_model", lambda name: load_model(path))
    choice = choose(load_config("gloam"), real[:3], _stub_features)
    assert choice.record["decision"] == "guard: gicp" and choice.config.method == "gicp"


def test_map_resolution_auto_follows_the_measured_rings(presets, real):
    dense = {"hdl64": 0.5, "os1-64": 0.5, "vlp16": 0.0, "hdl32": 0.0}
    for name, (_, measured, _) in presets.items():
        resolution, why = resolve_map_resolution("auto", measured)
        assert resolution == dense[name], f"{name}: {why}"
        assert f"{measured.rings} rings measured" in why
    assert resolve_map_resolution("auto", measure(real[:3]))[0] == 0.5  # real KITTI: HDL-64E
    assert resolve_map_resolution("auto", None) == (0.0, pytest.approx(
        "auto: the sensor could not be measured, so every keyframe's points"))  # fmt: skip
    assert resolve_map_resolution(0.25, None) == (0.25, "set")


@pytest.mark.parametrize("sensor", ["vlp16", "hdl64"])
def test_a_run_resolves_map_resolution_auto_as_the_number_would_run(presets, tmp_path, sensor):
    """``auto`` runs exactly as the number it resolves to, says which in metrics.json, and the
    Odometry API resolves it alike from its first raw scan."""
    root = presets[sensor][2]
    auto = dataclasses.replace(load_config("gicp"), map_resolution="auto")
    result = run_sequence(root, "00", auto, tmp_path / "auto", frames=2)
    resolution = {"vlp16": 0.0, "hdl64": 0.5}[sensor]
    written = json.loads((tmp_path / "auto" / "metrics.json").read_text())["map"]
    assert written == result["map"]
    assert written["setting"] == "auto" and written["resolution"] == resolution
    fixed = dataclasses.replace(auto, map_resolution=resolution)
    run_sequence(root, "00", fixed, tmp_path / "fixed", frames=2)
    poses = [np.loadtxt(tmp_path / run / "00_poses_kitti.txt") for run in ("auto", "fixed")]
    np.testing.assert_array_equal(*poses)
    scans = [read_scan(p) for p in sorted((root / "sequences/00/velodyne").glob("*.bin"))]
    odometry = Odometry(auto)
    odometry.register_frame(scans[0])
    assert odometry.config.map_resolution == resolution == odometry.map.resolution


def test_map_resolution_auto_needs_a_raw_scan_or_a_resolved_state(presets):
    root = presets["hdl64"][2]
    scan = read_scan(sorted((root / "sequences/00/velodyne").glob("*.bin"))[0])
    auto = dataclasses.replace(load_config("gicp"), map_resolution="auto")
    odometry = Odometry(auto)
    with pytest.raises(InputError, match="auto measures the sensor on the first raw scan"):
        odometry.register_frame(odometry.voxel_centres(scan), source="000000.bin")
    with pytest.raises(InputError, match="map_resolution: auto must be resolved"):
        Odometry(auto).restore({}, [])
