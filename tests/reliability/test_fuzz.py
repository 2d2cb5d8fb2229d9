"""Property-based fuzzing of the readers: mutated bytes of a valid npz, PLY, safetensors file and
rig folder, DGP scene and nuScenes tables either read or fail with the project's own error type (``DrivingSceneError``), never
another exception. Example counts are kept small for the suite's time (about a minute in all)."""

from __future__ import annotations

import json
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from drivingscene.errors import DrivingSceneError
from tests.factories import make_pair
from tests.reliability.corpus import ply_bytes, rig_folder, scene_arrays, tiny_weights, write_npz

FUZZ = settings(max_examples=150, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def work():
    folder = Path(tempfile.mkdtemp(prefix="fuzz_"))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def mutations(data: bytes):
    """Bit flips, byte overwrites, truncation and insertions of ``data``."""
    n = len(data)
    flips = st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, 7)), min_size=1, max_size=8).map(lambda fs: _flip(data, fs))
    overwrite = st.tuples(st.integers(0, n - 1), st.binary(min_size=1, max_size=16)).map(
        lambda t: data[: t[0]] + t[1] + data[t[0] + len(t[1]) :]
    )
    truncate = st.integers(0, n - 1).map(lambda k: data[:k])
    insert = st.tuples(st.integers(0, n), st.binary(min_size=1, max_size=16)).map(lambda t: data[: t[0]] + t[1] + data[t[0] :])
    return st.one_of(flips, overwrite, truncate, insert)


def _flip(data: bytes, flips) -> bytes:
    out = bytearray(data)
    for i, bit in flips:
        out[i] ^= 1 << bit
    return bytes(out)


def read_or_own_error(fn, *args):
    try:
        return fn(*args)
    except DrivingSceneError:
        return None


# ---- npz -------------------------------------------------------------------------------------


def _load_scene(path: Path):
    from drivingscene.data.frame_pair import FramePair, validate_frame_pair_file
    from drivingscene.data.npz import load_npz

    validate_frame_pair_file(path)
    return FramePair.from_arrays(load_npz(path), str(path))


@pytest.fixture(scope="module")
def npz_bytes(work):
    from drivingscene.data.npz import save_npz

    stored = save_npz(work / "stored.npz", scene_arrays(), compress=False).read_bytes()
    deflated = save_npz(work / "deflated.npz", scene_arrays(), compress=True).read_bytes()
    return stored, deflated


@FUZZ
@given(data=st.data(), compressed=st.booleans())
def test_npz_mutated_bytes(work, npz_bytes, data, compressed):
    path = work / "mutated.npz"
    path.write_bytes(data.draw(mutations(npz_bytes[compressed])))
    read_or_own_error(_load_scene, path)


@pytest.fixture(scope="module")
def recon_bytes(work):
    from drivingscene.gaussians.recon import save_reconstruction
    from tests.app.scenes import street_recon

    return save_reconstruction(street_recon(height=12, width=16), work / "recon.npz").read_bytes()


@FUZZ
@given(data=st.data())
def test_recon_npz_mutated_bytes(work, recon_bytes, data):
    """A saved reconstruction (what the viewer and `drivingscene render` open) with mutated bytes:
    read, or refused with the project's own one-line error."""
    from drivingscene.sources import open_source

    path = work / "mutated_recon.npz"
    path.write_bytes(data.draw(mutations(recon_bytes)))
    read_or_own_error(open_source, path)


KEYS = ["format", "version", "images", "intrinsics", "cam_to_ego", "ego_to_world", "timestamps", "camera_names", "gt_depth"]
ARRAYS = hnp.arrays(
    dtype=st.sampled_from([np.uint8, np.float32, np.float64, np.int64, np.bool_, np.dtype("<U3")]),
    shape=hnp.array_shapes(min_dims=0, max_dims=5, min_side=0, max_side=4),
)


@FUZZ
@given(replaced=st.dictionaries(st.sampled_from(KEYS), ARRAYS, max_size=4), dropped=st.sets(st.sampled_from(KEYS), max_size=2))
def test_random_arrays_dict(replaced, dropped):
    from drivingscene.data.frame_pair import FramePair

    arrays = {**scene_arrays(), **replaced}
    for key in dropped:
        arrays.pop(key, None)
    read_or_own_error(FramePair.from_arrays, arrays)


@settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(key=st.sampled_from(KEYS[:8]), member=st.binary(max_size=300))
def test_npz_random_member_bytes(work, key, member):
    import zipfile

    path = work / "member.npz"
    write_npz(path, scene_arrays())
    with zipfile.ZipFile(path, "a") as zf:
        zf.writestr(f"{key}_x.npy", member)
    read_or_own_error(_load_scene, path)


# ---- PLY -------------------------------------------------------------------------------------


@FUZZ
@given(data=st.data())
def test_ply_mutated(work, data):
    from drivingscene.export.ply import read_ply
    from drivingscene.sources import open_source

    good = ply_bytes(6)
    header_end = good.index(b"end_header") + len(b"end_header\n")
    part = data.draw(st.sampled_from(["header", "body", "any"]))
    if part == "header":
        head = data.draw(mutations(good[:header_end]))
        mutated = head + good[header_end:]
    elif part == "body":
        mutated = good[:header_end] + data.draw(mutations(good[header_end:]))
    else:
        mutated = data.draw(mutations(good))
    path = work / "mutated.ply"
    path.write_bytes(mutated)
    read_or_own_error(read_ply, path)
    read_or_own_error(open_source, path)


@FUZZ
@given(
    lines=st.lists(
        st.sampled_from(
            [
                "element vertex 2",
                "element vertex -1",
                "element vertex 99999999999",
                "element face 1",
                "property float x",
                "property uchar red",
                "property list uchar int vertex_indices",
                "property float128 x",
                "property double opacity",
                "format ascii 1.0",
                "format binary_big_endian 1.0",
                "comment x",
                "obj_info y",
            ]
        ),
        max_size=8,
    ),
    body=st.binary(max_size=64),
)
def test_ply_random_headers(work, lines, body):
    from drivingscene.export.ply import read_ply

    path = work / "header.ply"
    path.write_bytes(("ply\nformat binary_little_endian 1.0\n" + "\n".join(lines) + "\nend_header\n").encode() + body)
    read_or_own_error(read_ply, path)


# ---- safetensors -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def weights(work):
    path = tiny_weights(work / "weights" if (work / "weights").mkdir() is None else work)
    return path, path.read_bytes()


@settings(max_examples=80, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_safetensors_header(work, weights, data):
    import struct

    from drivingscene.methods.feedforward import load_model

    good_path, good = weights
    (length,) = struct.unpack("<Q", good[:8])
    header, body = good[8 : 8 + length], good[8 + length :]
    part = data.draw(st.sampled_from(["length", "header", "json"]))
    if part == "length":
        new_length = data.draw(st.one_of(st.integers(0, 2**64 - 1), st.integers(max(0, length - 64), length + 64)))
        mutated = struct.pack("<Q", new_length) + header + body
    elif part == "header":
        mutated = good[:8] + data.draw(mutations(header)) + body
        mutated = struct.pack("<Q", len(mutated) - 8 - len(body)) + mutated[8:]
    else:  # a JSON header of other tensors: names, dtypes, shapes, offsets
        entry = st.fixed_dictionaries(
            {
                "dtype": st.sampled_from(["F32", "F16", "I64", "BOOL", "XX"]),
                "shape": st.lists(st.integers(0, 2**40), max_size=3),
                "data_offsets": st.lists(st.integers(0, 2**40), min_size=2, max_size=2),
            }
        )
        text = json.dumps(data.draw(st.dictionaries(st.text(max_size=8), entry, max_size=3))).encode()
        mutated = struct.pack("<Q", len(text)) + text + body[:64]
    path = good_path.with_name("mutated.safetensors")
    path.write_bytes(mutated)
    path.with_suffix(".json").write_text(good_path.with_suffix(".json").read_text())
    read_or_own_error(load_model, path)


# ---- importers -------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rig(work):
    return rig_folder(work / "rig_source")


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**63) | st.floats() | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=4),
    max_leaves=12,
)


def _paths(node, prefix=()):
    """Every JSON path of ``node``."""
    yield prefix
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _paths(value, (*prefix, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _paths(value, (*prefix, i))


def mutated_json(data, text: str) -> str:
    """``text`` (a JSON document) with one value replaced or deleted somewhere, or its text damaged."""
    if data.draw(st.booleans()):
        doc = json.loads(text)
        paths = [p for p in _paths(doc) if p]
        if not paths:
            return json.dumps(data.draw(JSON_VALUES))
        path = data.draw(st.sampled_from(paths))
        node = doc
        for key in path[:-1]:
            node = node[key]
        if data.draw(st.booleans()):
            del node[path[-1]]
        else:
            node[path[-1]] = data.draw(JSON_VALUES)
        return json.dumps(doc)
    return data.draw(mutations(text.encode())).decode("utf-8", "replace")


def _fuzzed_copy(source: Path, folder: Path, data, relative: str) -> Path:
    """A fresh copy of ``source`` at ``folder`` with its JSON file ``relative`` mutated."""
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(source, folder)
    (folder / relative).write_text(mutated_json(data, (source / relative).read_text()))
    return folder


JSON_FUZZ = settings(max_examples=120, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@JSON_FUZZ
@given(data=st.data())
def test_rig_json_mutated(work, rig, data):
    from drivingscene.data.importers.rig import import_rig

    folder = _fuzzed_copy(rig, work / "rig_fuzz", data, "rig.json")
    read_or_own_error(import_rig, folder, (0, 1), (), None, "crop")


@pytest.fixture(scope="module")
def dgp(work):
    from tests.reliability.corpus import dgp_folder

    return dgp_folder(work / "dgp_source")


@JSON_FUZZ
@given(data=st.data(), relative=st.sampled_from(["scene_0.json", "calibration/c0.json"]))
def test_dgp_json_mutated(work, dgp, data, relative):
    """DGP (DDAD) scene and calibration files with a value replaced or deleted, or their text damaged."""
    from drivingscene.data.importers.ddad import import_ddad

    folder = _fuzzed_copy(dgp, work / "dgp_fuzz", data, relative)
    read_or_own_error(import_ddad, folder, (0, 1), (), None)


@pytest.fixture(scope="module")
def nuscenes_root(work, synth_pair):
    pytest.importorskip("nuscenes.nuscenes", reason="nuscenes-devkit not installed (make setup installs it)")
    from tests.data.importers.nuscenes_layout import write_nuscenes

    return write_nuscenes(synth_pair, work / "nuscenes_source")


NUSCENES_TABLES = ["scene", "sample", "sample_data", "calibrated_sensor", "ego_pose", "sensor", "log"]


@settings(max_examples=60, deadline=None, database=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data(), table=st.sampled_from(NUSCENES_TABLES))
def test_nuscenes_tables_mutated(work, nuscenes_root, data, table):
    """nuScenes tables, read through the real devkit, with a value replaced or deleted, or damaged text."""
    from drivingscene.data.importers.nuscenes import import_nuscenes
    from tests.data.importers.nuscenes_layout import SCENE, VERSION

    folder = work / "nuscenes_fuzz"
    shutil.rmtree(folder, ignore_errors=True)
    shutil.copytree(nuscenes_root, folder, symlinks=True)
    relative = f"{VERSION}/{table}.json"
    (folder / relative).write_text(mutated_json(data, (nuscenes_root / relative).read_text()))
    read_or_own_error(import_nuscenes, folder, VERSION, SCENE, 0, "keyframe", False, None)


def _refused_on_one_line(path: Path, expected: str = ""):
    """The scene file at ``path`` is one problem for `validate` and one line naming it for the
    loader (after the file's name, the regex ``expected``); the problem."""
    from drivingscene.data.frame_pair import load_frame_pair, validate_frame_pair_file
    from drivingscene.errors import InputError

    (problem,) = validate_frame_pair_file(path)
    assert problem.source == str(path)
    with pytest.raises(InputError, match=rf"^{re.escape(str(path))}: {expected}") as e:
        load_frame_pair(path)
    assert "\n" not in str(e.value)
    return problem


@pytest.mark.parametrize(
    ("offset", "value", "found"),
    [(6, b"\x54\x00", "zip file version 8.4"), (8, b"\x01\x00", "encrypted")],  # version needed; flag bit 0
    ids=["unknown-zip-version", "encrypted-member"],
)
def test_npz_central_directory_damage_is_one_line(work, npz_bytes, offset, value, found):
    """What the fuzzing found: zipfile raises NotImplementedError for a zip version it does not
    know and RuntimeError for a member flagged as encrypted; both are one line naming the file."""
    data = bytearray(npz_bytes[False])
    at = data.index(b"PK\x01\x02") + offset  # the first member's central directory entry
    data[at : at + 2] = value
    path = work / f"damaged_{offset}.npz"
    path.write_bytes(bytes(data))
    problem = _refused_on_one_line(path, rf"expected an \.npz archive.*{found}")
    assert found in problem.found


def test_npz_header_cut_inside_its_shape_is_one_line(work):
    """What fuzzing a reconstruction file found: a .npy header whose length field cuts it inside the
    shape tuple makes numpy's second parse of it raise tokenize.TokenError (not a ValueError)."""
    import struct

    from drivingscene.data.npz import save_npz

    # the images' .npy header (version 1.0: a 2-byte length) in a scene whose images are larger than
    # zipfile's first read (4 KiB), so that their CRC is not checked before the header is parsed
    arrays = make_pair(num_views=2, height=48, width=64, with_gt=False).to_arrays()
    data = bytearray(save_npz(work / "larger.npz", arrays, compress=False).read_bytes())
    magic = data.index(b"images.npy\x93NUMPY") + len(b"images.npy")
    start = magic + 10
    cut = data.index(b"'shape': (", start) + len(b"'shape': (")
    cut = data.index(b", ", cut) + 2  # "(2, " and no more
    data[magic + 8 : magic + 10] = struct.pack("<H", cut - start)
    path = work / "header_cut.npz"
    path.write_bytes(bytes(data))
    _refused_on_one_line(path)
