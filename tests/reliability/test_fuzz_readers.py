"""Fuzzing the readers through the real CLI: every malformed input is refused cleanly.

A clean refusal is what :func:`tests.test_bad_input.assert_refused` checks (non-zero exit, one
stderr line starting with ``error: ``) plus two things a user needs: the line names the
problem (each case lists fragments it must contain) and is not a bare Python exception
(``error: TypeError: ...`` is the CLI's fallback for errors nobody anticipated). And no
output is left: the destination does not exist afterwards, or, for ``reconstruct``, it is
absent or not marked complete.

Cases that currently fail this are marked ``xfail(strict=True, reason="BUG: ...")``: the
bug is real and the case starts passing (and the mark must go) once it is fixed.
"""

import io
import json
import os
import pickle
import re
import struct
import zipfile

import numpy as np
import pytest
import zarr
from zarr.codecs import ZstdCodec

from tests.test_bad_input import assert_refused

RNG = np.random.default_rng(20240607)
FRAMES, HEIGHT, WIDTH = 45, 8, 16
SPIKES = (RNG.random((FRAMES, HEIGHT, WIDTH)) < 0.2).astype(np.uint8)
PACKED = np.packbits(SPIKES, axis=-1, bitorder="little")  # (45, 8, 2)
PY_EXCEPTION = re.compile(r"^error: (?:[A-Za-z_][\w.]*(?:Error|Exception)|error): ")


def assert_clean_refusal(result, *fragments):
    assert_refused(result, *fragments)
    line = result.stderr.strip()
    assert not PY_EXCEPTION.match(line), f"a bare Python exception, not a message naming the problem: {line}"


def case(case_id, *values, bug=None):
    marks = [pytest.mark.xfail(strict=True, reason=f"BUG: {bug}")] if bug else []
    return pytest.param(*values, id=case_id, marks=marks)


# --- cscsr ingest -----------------------------------------------------------------------------

def npy_bytes(array) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def npz_bytes(**arrays) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def zip_member(data: bytes, name="spk.npy", compression=zipfile.ZIP_STORED) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as archive:
        archive.writestr(name, data)
    return buffer.getvalue()


def npy_with_header(header: str, data: bytes = bytes(5000)) -> bytes:
    """A version 1.0 .npy file with a hand-written header dict (padded as numpy pads it)."""
    text = header.encode("latin1")
    text += b" " * ((64 - (10 + len(text) + 1) % 64) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text + data


def shape_header(shape: str, descr: str = "|u1") -> bytes:
    return npy_with_header(f"{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}")


def corrupt_deflate() -> bytes:
    archive = bytearray(zip_member(npy_bytes(SPIKES), compression=zipfile.ZIP_DEFLATED))
    archive[60:80] = RNG.bytes(20)  # inside the deflate stream, after the local header
    return bytes(archive)


def dat_bytes(bits=SPIKES) -> bytes:
    return np.packbits(bits.reshape(bits.shape[0], -1), axis=-1, bitorder="little").tobytes()


GEOMETRY = ["--height", HEIGHT, "--width", WIDTH]
VALID_NPY = npy_bytes(SPIKES)
VALID_NPZ = npz_bytes(spk=SPIKES)
INPUT = "{input}"  # a fragment standing for the input's path

INGEST_CASES = [
    # empty files
    case("dat-empty", "c.dat", b"", GEOMETRY, ["capture is empty"]),
    case("npy-empty", "c.npy", b"", [], [INPUT, "not a valid .npy array"]),
    case("npz-empty", "c.npz", b"", [], [INPUT, "not a valid .npz archive"]),
    # truncated .npy
    case("npy-cut-after-magic", "c.npy", VALID_NPY[:8], [], [INPUT, "not a valid .npy array"]),
    case("npy-cut-in-header", "c.npy", VALID_NPY[:30], [], [INPUT, "not a valid .npy array"]),
    case("npy-cut-in-data", "c.npy", VALID_NPY[:-100], [], [INPUT, "is truncated", "frame 44 of 45"]),
    case("npy-header-only", "c.npy", VALID_NPY[: len(VALID_NPY) - SPIKES.nbytes], [],
         [INPUT, "is truncated", "promises 45 frames"]),
    # random bytes
    case("npy-random-bytes", "c.npy", RNG.bytes(700), [], [INPUT, "not a valid .npy array"]),
    case("npz-random-bytes", "c.npz", RNG.bytes(700), [], [INPUT, "not a valid .npz archive"]),
    case("npz-cut-archive", "c.npz", VALID_NPZ[: len(VALID_NPZ) // 2], [], [INPUT, "not a valid .npz archive"]),
    case("npz-member-random-bytes", "c.npz", zip_member(RNG.bytes(300)), [], [INPUT, "not a valid .npy array"]),
    case("npz-member-cut-in-data", "c.npz", zip_member(VALID_NPY[:-100]), [], [INPUT, "is truncated"]),
    case("npz-member-corrupt-deflate", "c.npz", corrupt_deflate(), [], [INPUT, "decompressing"]),
    # keys
    case("npz-without-key", "c.npz", npz_bytes(other=SPIKES, more=SPIKES), [],
         [INPUT, "no array 'spk'", "other, more"]),
    case("npz-no-arrays", "c.npz", npz_bytes(), [], [INPUT, "no array 'spk'", "nothing"]),
    case("npz-named-key-missing", "c.npz", VALID_NPZ, ["--key", "nope"], [INPUT, "no array 'nope'", "spk"]),
    # dtypes and values (0/1 floats and int16 are accepted by design: see test_binary_arrays_of_other_dtypes...)
    case("npz-float-non-binary", "c.npz", npz_bytes(spk=SPIKES.astype(np.float32) * 0.5), [],
         ["must be 0 or 1", "found 0.5"]),
    case("npz-float-nan", "c.npz", npz_bytes(spk=np.where(SPIKES, np.nan, 0.0)), [], ["must be 0 or 1", "nan"]),
    case("npz-int16-negative", "c.npz", npz_bytes(spk=-SPIKES.astype(np.int16)), [], ["must be 0 or 1", "found -1"]),
    case("npz-int16-256", "c.npz", npz_bytes(spk=SPIKES.astype(np.int16) * 256), [], ["must be 0 or 1", "found 256"]),
    case("npz-values-2", "c.npz", npz_bytes(spk=SPIKES * 2), [], ["must be 0 or 1", "found 2 at frame 0"]),
    case("npy-values-255", "c.npy", npy_bytes(SPIKES * 255), [], ["must be 0 or 1", "found 255"]),
    case("npy-complex-dtype", "c.npy", npy_bytes(SPIKES.astype(np.complex64)), [], ["dtype complex64"]),
    case("npy-string-dtype", "c.npy", npy_bytes(SPIKES.astype("U1")), [], ["dtype <U1"]),
    case("npy-object-dtype-pickled", "c.npy", npy_bytes(np.full((2, 2, 2), None, object)), [], ["dtype object"]),
    case("npy-fortran-order", "c.npy", npy_bytes(np.asfortranarray(SPIKES)), [], [INPUT, "Fortran-ordered"]),
    # ranks and shapes
    case("npz-rank-2", "c.npz", npz_bytes(spk=SPIKES[0]), [], ["rank 2", "expected (T, H, W)"]),
    case("npz-rank-4", "c.npz", npz_bytes(spk=SPIKES[None]), [], ["rank 4", "expected (T, H, W)"]),
    case("npy-rank-0", "c.npy", npy_bytes(np.uint8(1)), [], ["rank 0"]),
    case("npy-zero-frames", "c.npy", npy_bytes(SPIKES[:0]), [], ["empty", "(0, 8, 16)"]),
    # hand-made headers
    case("npy-header-huge-frame-count", "c.npy", shape_header("(1000000000000, 8, 16)"), [],
         [INPUT, "is truncated", "promises 1000000000000 frames"]),
    case("npz-header-huge-frame-count", "c.npz", zip_member(shape_header("(1000000000000, 8, 16)")), [],
         [INPUT, "is truncated"]),
    case("npy-header-huge-frame-size", "c.npy", shape_header(f"(1, {2**31}, {2**31})"), [], [INPUT, "truncated"]),
    case("npy-header-overflowing-shape", "c.npy", shape_header(f"({2**62}, {2**62}, {2**62})"), [],
         [INPUT, "truncated"]),
    case("npy-header-negative-shape", "c.npy", shape_header("(-41, 8, 16)"), [], ["nonsense shape (-41, 8, 16)"]),
    case("npy-header-bool-dimension", "c.npy", shape_header("(41, 8, True)"), [], ["nonsense shape (41, 8, True)"]),
    case("npy-header-not-a-literal", "c.npy", npy_with_header("{'descr': '|u1', "), [],
         [INPUT, "not a valid .npy array"]),
    case("npy-header-not-a-dict", "c.npy", npy_with_header("[1, 2, 3]"), [], [INPUT, "not a valid .npy array"]),
    case("npy-header-bad-descr", "c.npy", shape_header("(41, 8, 16)", descr="zz"), [],
         [INPUT, "not a valid .npy array"]),
    case("npy-header-float-dimension", "c.npy", shape_header("(41, 8, 16.5)"), [], [INPUT, "not a valid .npy array"]),
    case("npy-header-length-beyond-file", "c.npy", b"\x93NUMPY\x01\x00" + struct.pack("<H", 65535) + b"{", [],
         [INPUT, "not a valid .npy array"]),
    case("npy-v2-header-length-beyond-file", "c.npy", b"\x93NUMPY\x02\x00" + struct.pack("<I", 2**31) + b"{", [],
         [INPUT, "not a valid .npy array"]),
    # .dat geometry
    case("dat-size-not-a-multiple", "c.dat", dat_bytes()[:-5], GEOMETRY,
         ["not a multiple of the frame size 16", "11 bytes too many"]),
    case("dat-no-geometry", "c.dat", dat_bytes(), [], ["give both --height and --width"]),
    case("dat-width-0", "c.dat", dat_bytes(), ["--height", 8, "--width", 0],
         ["width must be a positive integer, got 0"]),
    case("dat-height-0", "c.dat", dat_bytes(), ["--height", 0, "--width", 16],
         ["height must be a positive integer, got 0"]),
    case("dat-height-negative", "c.dat", dat_bytes(), ["--height", -8, "--width", 16],
         ["height must be a positive integer, got -8"]),
    case("dat-width-negative", "c.dat", dat_bytes(), ["--height", 8, "--width", -16],
         ["width must be a positive integer, got -16"]),
    case("dat-head-columns-negative", "c.dat", dat_bytes(), [*GEOMETRY, "--head-columns", -3],
         ["head columns must be >= 0, got -3"]),
    case("dat-huge-geometry", "c.dat", dat_bytes(), ["--height", 10**9, "--width", 10**9],
         ["not a multiple of the frame size"]),
    case("dat-fps-0", "c.dat", dat_bytes(), [*GEOMETRY, "--fps", 0], ["fps must be > 0"]),
    case("dat-fps-nan", "c.dat", dat_bytes(), [*GEOMETRY, "--fps", "nan"], ["fps must be > 0"]),
    case("dat-unknown-reset", "c.dat", dat_bytes(), [*GEOMETRY, "--reset", "half"], ["unknown reset mode 'half'"]),
]


@pytest.mark.parametrize("name,data,args,fragments", INGEST_CASES)
def test_ingest_refuses(cli, tmp_path, name, data, args, fragments):
    source = tmp_path / name
    source.write_bytes(data)
    out = tmp_path / "s.zarr"
    result = cli("ingest", source, out, *args)
    assert_clean_refusal(result, *[str(source) if f == INPUT else f for f in fragments])
    assert not out.exists()
    assert os.listdir(tmp_path) == [name]  # nothing else left behind either


def test_binary_arrays_of_other_dtypes_are_accepted(cli, tmp_path):
    """By design (stages.capture.spike_arrays) 0/1 floats, int16 and booleans are spike arrays too."""
    for dtype in (np.float32, np.float64, np.int16, np.bool_):
        np.savez(tmp_path / "a.npz", spk=SPIKES.astype(dtype))
        result = cli("ingest", tmp_path / "a.npz", tmp_path / "s.zarr", "--overwrite")
        assert result.exit_code == 0, result.stderr
        assert zarr.open_group(str(tmp_path / "s.zarr"), mode="r").attrs["spike_count"] == int(SPIKES.sum())


# --- cscsr info / export / reconstruct of damaged spike stores -------------------------------------

GOOD_ATTRS = {"height": HEIGHT, "width": WIDTH, "cfa": "rggb", "fps": 20000.0, "source": "fuzz", "flipped": False,
              "head_columns": 0, "reset": "subtract", "format_version": 1, "state": "complete",
              "spike_count": int(SPIKES.sum())}


def make_store(path, *, attrs=None, spikes=PACKED, drop=(), **changes):
    """A spike store made with zarr directly: the layout ingest writes, with ``changes`` to its attributes."""
    values = {k: v for k, v in (GOOD_ATTRS if attrs is None else attrs).items() if k not in drop}
    values.update(changes)
    group = zarr.open_group(str(path), mode="w", attributes=values)
    if spikes is not None:
        chunks = (20, *spikes.shape[1:]) if spikes.ndim >= 1 else ()
        group.create_array("spikes", data=spikes, chunks=chunks, compressors=ZstdCodec(level=1),
                           config={"write_empty_chunks": True})
    return group


def write(path, relative, text):
    with open(os.path.join(path, relative), "w") as handle:
        handle.write(text)


def spikes_group(path):
    make_store(path, spikes=None).create_group("spikes")


def root_array(path):
    zarr.create_array(str(path), data=PACKED, attributes=GOOD_ATTRS)


def a_file(path):
    path.write_bytes(b"not a store")


def chunk_files(path):
    root = os.path.join(path, "spikes", "c")
    return sorted(os.path.join(d, f) for d, _, files in os.walk(root) for f in files)


def corrupt_chunk(path):
    make_store(path)
    first = chunk_files(path)[0]
    with open(first, "rb") as handle:
        data = handle.read()
    with open(first, "wb") as handle:
        handle.write(data[: len(data) // 2])


def missing_chunk(path):
    make_store(path)
    os.remove(chunk_files(path)[1])


ALL = ("info", "export", "reconstruct")
READERS = ("export", "reconstruct")  # info shows unfinished stores on purpose (test_info_shows_an_unfinished_store)
STORE = "{store}"  # a fragment standing for the store's path

NOT_JSON = ("the store's metadata is not valid JSON and the message is the bare json error "
            "('Expecting ... line 1 column ...'), naming neither the store nor zarr.json")
STORE_CASES = [
    # (id, build(path), commands, fragments, bug)
    ("no-spikes-array", lambda p: make_store(p, spikes=None), ALL, [STORE, "has no 'spikes' array"], None),
    ("spikes-is-a-group", spikes_group, ALL, [STORE, "spikes"], None),
    ("spikes-float32", lambda p: make_store(p, spikes=PACKED.astype(np.float32)), ALL,
     [STORE, "'spikes' is float32 (45, 8, 2), expected uint8 (T, 8, 2)"], None),
    ("spikes-rank-2", lambda p: make_store(p, spikes=PACKED[0]), ALL, [STORE, "'spikes' is uint8 (8, 2)"], None),
    ("spikes-rank-4", lambda p: make_store(p, spikes=PACKED[None]), ALL,
     [STORE, "'spikes' is uint8 (1, 45, 8, 2)"], None),
    ("no-attributes", lambda p: make_store(p, attrs={}), ALL, ["attributes lack height, width, cfa"], None),
    ("attrs-without-height", lambda p: make_store(p, drop=("height",)), ALL, ["attributes lack height"], None),
    ("attrs-without-width", lambda p: make_store(p, drop=("width",)), ALL, ["attributes lack width"], None),
    ("attrs-without-cfa", lambda p: make_store(p, drop=("cfa",)), ALL, ["attributes lack cfa"], None),
    ("height-abc", lambda p: make_store(p, height="abc"), ALL, [STORE, "height must be an integer, got 'abc'"], None),
    ("height-negative", lambda p: make_store(p, height=-8), ALL, [STORE, "height must be positive, got -8"], None),
    ("height-zero", lambda p: make_store(p, height=0), ALL, [STORE, "height must be positive, got 0"], None),
    ("height-fraction", lambda p: make_store(p, height=8.5), ALL, [STORE, "height must be an integer, got 8.5"], None),
    ("width-not-matching-packed-array", lambda p: make_store(p, width=40), ALL,
     [STORE, "'spikes' is uint8 (45, 8, 2), expected uint8 (T, 8, 5)"], None),
    ("width-zero", lambda p: make_store(p, width=0), ALL, [STORE, "width must be positive, got 0"], None),
    ("cfa-xyz", lambda p: make_store(p, cfa="xyz"), ALL, ["unknown CFA 'xyz'"], None),
    ("cfa-number", lambda p: make_store(p, cfa=5), ALL, [STORE, "cfa must be a string, got 5"], None),
    ("fps-text", lambda p: make_store(p, fps="fast"), ALL, [STORE, "fps must be a number, got 'fast'"], None),
    ("fps-zero", lambda p: make_store(p, fps=0), ALL, ["fps must be > 0"], None),
    ("reset-unknown", lambda p: make_store(p, reset="half"), ALL, ["unknown reset mode 'half'"], None),
    ("state-writing", lambda p: make_store(p, state="writing"), READERS, [STORE, "incomplete (state 'writing')"], None),
    ("state-missing", lambda p: make_store(p, drop=("state",)), READERS, [STORE, "incomplete (state None)"], None),
    ("zarr-json-not-json", lambda p: (make_store(p), write(p, "zarr.json", "{not json")), ALL, [STORE], None),
    ("zarr-json-empty", lambda p: (make_store(p), write(p, "zarr.json", "")), ALL, [STORE], None),
    ("zarr-json-a-list", lambda p: (make_store(p), write(p, "zarr.json", "[1, 2]")), ALL, [STORE], None),
    ("zarr-json-attributes-a-list",
     lambda p: (make_store(p), write(p, "zarr.json", json.dumps({"zarr_format": 3, "node_type": "group",
                                                                 "attributes": [1]}))), ALL, [STORE], None),
    ("spikes-zarr-json-not-json", lambda p: (make_store(p), write(p, "spikes/zarr.json", "{oops")), ALL, [STORE], None),
    ("root-is-an-array", root_array, ALL, [STORE, "holds a Zarr array, not a group"], None),
    ("path-is-a-file", a_file, ALL, [STORE, "no Zarr group there"], None),
    ("empty-directory", lambda p: p.mkdir(), ALL, [STORE, "no Zarr group there"], None),
    ("chunk-damaged", corrupt_chunk, READERS, [STORE, "a chunk is damaged"], None),
    ("chunk-missing", missing_chunk, ("export",), [STORE, "is missing (lost data)"], None),
    ("flipped-text", lambda p: make_store(p, flipped="no"), ("export",), [STORE, "flipped must be true or false"], None),
    ("head-columns-text", lambda p: make_store(p, head_columns="x"), ("export",), [STORE, "head_columns must be an integer"],
     None),
    ("head-columns-negative", lambda p: make_store(p, head_columns=-8), ("export",),
     ["head columns must be >= 0"], None),
    ("gain-text", lambda p: make_store(p, gain="x"), ("reconstruct",), [STORE, "gain must be a number"], None),
    ("gain-negative", lambda p: make_store(p, gain=-1.0), ("reconstruct",), ["gain must be > 0, got -1.0"], None),
    ("scale-text", lambda p: make_store(p, scale="x"), ("reconstruct",), [STORE, "scale must be an integer"], None),
    ("spike-count-text", lambda p: make_store(p, spike_count="x"), ("info",), [STORE, "spike_count must be an integer"],
     None),
]


def store_params():
    for case_id, build, commands, fragments, bug in STORE_CASES:
        for command in commands:
            yield case(f"{command}-{case_id}", command, build, fragments, bug=bug)


def run_on_store(cli, command, store, tmp_path):
    """Run ``command`` on ``store``; return (result, the output it must not leave)."""
    if command == "info":
        return cli("info", store), None
    if command == "export":
        out = tmp_path / "out.dat"
        return cli("export", store, out), out
    out = tmp_path / "out.zarr"
    return cli("reconstruct", store, out, "--workers", 1), out


def assert_no_output(command, out):
    if out is None:
        return
    if command == "reconstruct" and out.exists():
        state = dict(zarr.open_group(str(out), mode="r").attrs).get("state")
        assert state != "complete", f"{out} is marked complete after a failure"
    elif command != "reconstruct":
        assert not out.exists()
        assert not os.path.exists(f"{out}.partial")


@pytest.mark.parametrize("command,build,fragments", list(store_params()))
def test_damaged_store_is_refused(cli, tmp_path, command, build, fragments):
    store = tmp_path / "s.zarr"
    build(store)
    result, out = run_on_store(cli, command, store, tmp_path)
    assert_clean_refusal(result, *[str(store) if f == STORE else f for f in fragments])
    assert_no_output(command, out)


def test_hand_made_store_is_accepted(cli, tmp_path):
    """The control: the store the damaged cases start from passes every reader."""
    store = tmp_path / "s.zarr"
    make_store(store)
    assert cli("info", store).exit_code == 0
    result = cli("export", store, tmp_path / "out.dat")
    assert result.exit_code == 0, result.stderr
    assert (tmp_path / "out.dat").read_bytes() == dat_bytes()
    result = cli("reconstruct", store, tmp_path / "out.zarr", "--workers", 1)
    assert result.exit_code == 0, result.stderr
    assert zarr.open_group(str(tmp_path / "out.zarr"), mode="r").attrs["state"] == "complete"


def test_info_shows_an_unfinished_store(cli, tmp_path):
    make_store(tmp_path / "s.zarr", state="writing")
    result = cli("info", tmp_path / "s.zarr", "--json")
    assert result.exit_code == 0, result.stderr
    assert json.loads(result.stdout)["state"] == "writing"


# --- cscsr model-info / reconstruct --method cscsr with bad weights ----------------------------------

class Tripwire:
    """Unpickling this creates a directory: proof that a weights file was unpickled."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return os.mkdir, (self.marker,)


def safetensors_bytes(metadata, tensors=None) -> bytes:
    import torch
    from safetensors.torch import save

    return save(tensors or {"x": torch.zeros(3)}, metadata=metadata)


def torch_pickle(marker, **kwargs) -> bytes:
    import torch

    buffer = io.BytesIO()
    torch.save({"weight": torch.zeros(2), "tripwire": Tripwire(marker)}, buffer, **kwargs)
    return buffer.getvalue()


def raw_header(header) -> bytes:
    text = json.dumps(header).encode()
    return struct.pack("<Q", len(text)) + text


@pytest.fixture(scope="module")
def weights_dir(tmp_path_factory):
    """Valid lite weights (to cut and tamper with) and a Bayer store of 45 frames for reconstruct."""
    from cscsr.network.config import named
    from cscsr.network.model import CSCSR
    from cscsr.weights.weights_io import save_weights

    folder = tmp_path_factory.mktemp("weights")
    save_weights(CSCSR(named("lite")), folder / "good.safetensors")
    make_store(folder / "store.zarr")
    return folder


def good(folder) -> bytes:
    return (folder / "good.safetensors").read_bytes()


def header_length(folder) -> int:
    return struct.unpack("<Q", good(folder)[:8])[0]


def meta(**values):
    return {"format": "cscsr-weights/1", **values}


def config(**values):
    return json.dumps({"name": "fuzz", **values})


def mismatched_tensors(folder) -> bytes:
    from safetensors.torch import load_file

    from cscsr.network.config import named

    return safetensors_bytes(meta(config=named("full").to_json()), load_file(folder / "good.safetensors"))


WEIGHTS = "{weights}"  # a fragment standing for the weights file's path
NOT_SAFETENSORS = [WEIGHTS, "is not a safetensors file"]
WEIGHTS_CASES = [
    # (id, make(folder, marker) -> bytes or None for a directory, fragments, bug)
    ("empty", lambda f, m: b"", [WEIGHTS, "not a safetensors file (only 0 bytes)"], None),
    ("three-bytes", lambda f, m: b"\x01\x02\x03", [WEIGHTS, "(only 3 bytes)"], None),
    ("random-bytes", lambda f, m: RNG.bytes(4096), NOT_SAFETENSORS, None),
    ("torch-save-pickle", lambda f, m: torch_pickle(m), NOT_SAFETENSORS, None),
    ("torch-save-legacy-pickle", lambda f, m: torch_pickle(m, _use_new_zipfile_serialization=False),
     NOT_SAFETENSORS, None),
    ("plain-pickle", lambda f, m: pickle.dumps({"tripwire": Tripwire(m)}), NOT_SAFETENSORS, None),
    ("safetensors-without-metadata", lambda f, m: safetensors_bytes(None),
     [WEIGHTS, "not a cscsr weights file", "metadata format None"], None),
    ("safetensors-other-format", lambda f, m: safetensors_bytes({"format": "pt"}),
     [WEIGHTS, "not a cscsr weights file", "'pt'"], None),
    ("cscsr-format-without-config", lambda f, m: safetensors_bytes(meta()),
     [WEIGHTS, "no valid network configuration"], None),
    ("config-not-json", lambda f, m: safetensors_bytes(meta(config="{oops")),
     [WEIGHTS, "no valid network configuration"], None),
    ("config-unknown-field", lambda f, m: safetensors_bytes(meta(config=config(bogus=1))),
     [WEIGHTS, "unknown configuration fields bogus"], None),
    ("config-even-frames", lambda f, m: safetensors_bytes(meta(config=config(frames=40))),
     [WEIGHTS, "must be odd"], None),
    ("config-negative-features", lambda f, m: safetensors_bytes(meta(config=config(features=-4))),
     [WEIGHTS, "features must be a positive integer, got -4"], None),
    ("tensors-not-matching-config", lambda f, m: safetensors_bytes(meta(config=config())),
     [WEIGHTS, "does not match its configuration 'fuzz'"], None),
    ("lite-tensors-full-config", lambda f, m: mismatched_tensors(f),
     [WEIGHTS, "does not match its configuration 'full'"], None),
    ("cut-in-header", lambda f, m: good(f)[: 8 + header_length(f) // 2], NOT_SAFETENSORS, None),
    ("cut-in-data", lambda f, m: good(f)[: len(good(f)) // 2], [WEIGHTS, "is damaged"], None),
    ("cut-last-byte", lambda f, m: good(f)[:-1], [WEIGHTS, "is damaged"], None),
    ("header-not-utf8", lambda f, m: struct.pack("<Q", 4) + b"\xff\xfe\xfd\xfc", [WEIGHTS, "header is not JSON"], None),
    ("header-a-json-list", lambda f, m: raw_header([1]), [WEIGHTS, "header is not a JSON object"], None),
    ("metadata-a-json-list", lambda f, m: raw_header({"__metadata__": [1]}), [WEIGHTS, "not a cscsr weights file"],
     None),
    ("a-directory", lambda f, m: None, [WEIGHTS, "is a folder, not a weights file"], None),
]


def weights_params():
    for case_id, make, fragments, bug in WEIGHTS_CASES:
        for command in ("model-info", "reconstruct"):
            yield case(f"{command}-{case_id}", command, case_id, make, fragments, bug=bug)


@pytest.mark.parametrize("command,case_id,make,fragments", list(weights_params()))
def test_bad_weights_are_refused(cli, weights_dir, tmp_path, command, case_id, make, fragments):
    marker = str(tmp_path / "UNPICKLED")
    weights = tmp_path / f"{case_id}.safetensors"
    data = make(weights_dir, marker)
    if data is None:
        weights.mkdir()
    else:
        weights.write_bytes(data)
    out = tmp_path / "out.zarr"
    if command == "model-info":
        result = cli("model-info", "--weights", weights)
    else:
        result = cli("reconstruct", weights_dir / "store.zarr", out, "--method", "cscsr", "--weights", weights,
                     "--workers", 1)
    assert not os.path.exists(marker), "the weights file was unpickled"
    assert_clean_refusal(result, *[str(weights) if f == WEIGHTS else f for f in fragments])
    assert not out.exists()


def test_good_weights_are_accepted(cli, weights_dir):
    """The control: the file the cut cases start from is a valid weights file."""
    result = cli("model-info", "--weights", weights_dir / "good.safetensors")
    assert result.exit_code == 0, result.stderr
    assert "lite" in result.stdout
