"""Every reader, fed any bytes, either returns a valid result or raises InputError naming the
file: never another exception. Inputs are arbitrary bytes and mutations of valid files
(truncated, bytes flipped, header numbers changed); examples are derandomised, so CI runs the
same ones every time."""

import json
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gloam_jax import io
from gloam_jax.config import load_config
from gloam_jax.errors import InputError
from gloam_jax.models import load_model, save_model

FUZZ = settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def _pcd(binary: bool) -> bytes:
    points = np.random.default_rng(0).normal(size=(5, 4)).astype(np.float32)
    head = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\n"
        "COUNT 1 1 1 1\nWIDTH 5\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 5\n"
    )
    if binary:
        return (head + "DATA binary\n").encode() + points.tobytes()
    rows = "\n".join(" ".join(f"{v:.4f}" for v in p) for p in points)
    return (head + "DATA ascii\n" + rows + "\n").encode()


def _ply() -> bytes:
    points = np.random.default_rng(1).normal(size=(4, 3)).astype("<f4")
    head = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\n"
        "property float y\nproperty float z\nend_header\n"
    )
    return head.encode() + points.tobytes()


def _ply_ascii() -> bytes:
    head = (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nproperty float intensity\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    return (head + "0 1 2 0.5\n1 2 3 0.25\n2 3 4 1\n3 0 1 2\n").encode()


def _npy() -> bytes:
    import io as pyio

    buffer = pyio.BytesIO()
    np.save(buffer, np.random.default_rng(2).normal(size=(6, 4)).astype(np.float32))
    return buffer.getvalue()


VALID = {
    "scan.bin": np.random.default_rng(3).normal(size=(8, 4)).astype(np.float32).tobytes(),
    "scan.pcd": _pcd(binary=True),
    "ascii.pcd": _pcd(binary=False),
    "scan.ply": _ply(),
    "ascii.ply": _ply_ascii(),
    "scan.npy": _npy(),
    "000000.label": np.arange(8, dtype=np.uint32).tobytes(),
    "poses.txt": b"1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1.5 0 1 0 0 0 0 1 0.2\n",
    "tum.txt": b"# t x y z qx qy qz qw\n0.0 1 2 3 0 0 0 1\n0.1 1.1 2 3 0 0 0.1 0.99\n",
    "calib.txt": b"P0: 7 0 6 0 0 7 1 0 0 0 1 0\nTr: 0 -1 0 0 0 0 -1 0 1 0 0 0\n",
    "times.txt": b"0.0\n0.1\n0.2\n",
    "settings.yaml": b"mode: frame_to_frame\npreprocess:\n  min_range: 2.0\ngicp:\n"
    b"  num_candidates: 3\n",
}


@st.composite
def mutations(draw, valid: bytes) -> bytes:
    """A valid file truncated, with bytes flipped or inserted, or with a number changed."""
    data = bytearray(valid)
    kind = draw(st.sampled_from(["truncate", "flip", "insert", "number", "random"]))
    if kind == "truncate":
        return bytes(data[: draw(st.integers(0, max(len(data) - 1, 0)))])
    if kind == "flip":
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, len(data) - 1))
            data[i] = draw(st.integers(0, 255))
        return bytes(data)
    if kind == "insert":
        i = draw(st.integers(0, len(data)))
        return bytes(data[:i]) + draw(st.binary(max_size=16)) + bytes(data[i:])
    if kind == "number":
        numbers = list(re.finditer(rb"-?\d+(\.\d+)?", bytes(data[:400])))
        if numbers:
            m = draw(st.sampled_from(numbers))
            new = draw(
                st.sampled_from([b"-1", b"0", b"-7", b"99999999999", b"1e400", b"nan", b"x"])
            )
            return bytes(data[: m.start()]) + new + bytes(data[m.end() :])
    return draw(st.binary(max_size=256))


def _reader(name: str):
    readers = {
        ".bin": io.read_scan, ".pcd": io.read_scan, ".ply": io.read_scan, ".npy": io.read_scan,
        ".label": io.read_labels, "poses.txt": io.read_kitti_poses, "tum.txt": io.read_tum_poses,
        "calib.txt": io.read_calib, "times.txt": io.read_times, ".yaml": load_config,
    }  # fmt: skip
    return next(f for key, f in readers.items() if name.endswith(key))


def _check(reader, path) -> None:
    try:
        result = reader(path)
    except InputError as err:
        assert str(path.name) in str(err), err  # the message names the file
        return
    for a in result if isinstance(result, tuple) else [result]:
        if isinstance(a, np.ndarray):
            assert a.dtype.kind in "fiu"


@pytest.mark.parametrize("name", sorted(VALID))
def test_valid_files_read(tmp_path, name):
    (tmp_path / name).write_bytes(VALID[name])
    _reader(name)(tmp_path / name)


@pytest.mark.parametrize("name", sorted(VALID))
def test_any_bytes_give_a_result_or_an_input_error(tmp_path, name):
    reader = _reader(name)

    @FUZZ
    @given(data=mutations(VALID[name]))
    def run(data):
        path = tmp_path / name
        path.write_bytes(data)
        _check(reader, path)

    run()


def test_model_files(tmp_path):
    import jax

    from gloam_jax.features import fit_pca
    from gloam_jax.models import init_model

    pca = fit_pca(np.random.default_rng(0).normal(size=(40, 8)))
    save_model(tmp_path / "m.npz", init_model(jax.random.PRNGKey(0), pca))
    valid = (tmp_path / "m.npz").read_bytes()

    @FUZZ
    @given(data=mutations(valid))
    def run(data):
        path = tmp_path / "fuzzed.npz"
        path.write_bytes(data)
        try:
            load_model(path)
        except InputError as err:
            assert "fuzzed.npz" in str(err)

    run()
    # A well-formed archive with a wrong metadata entry is refused too.
    with np.load(tmp_path / "m.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["metadata"] = np.array(json.dumps({"format": "gloam-jax-model", "version": 1}))
    np.savez(tmp_path / "meta.npz", **arrays)
    with pytest.raises(InputError, match="meta.npz"):
        load_model(tmp_path / "meta.npz")
