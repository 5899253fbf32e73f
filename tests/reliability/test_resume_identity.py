"""``--resume`` checks what an output was made from, not only the paths it was made from (issue 34, point 3).

A job is interrupted for real: one chunk of its input is taken away, so the tasks that read it fail and the
job ends ``JobIncomplete`` with the other tasks committed (what ``--resume`` exists for). Then another
recording is put at the input's path, or other weights at the weights' path, and ``--resume`` must refuse
with one line naming what changed, leaving the output as it was; with the same input and weights (the chunk
put back) it must finish with the bytes of an uninterrupted run. Stores from before identities (no
``identity`` attribute) are told apart by what their writer recorded (spike count, source, shape); outputs
from before the record are resumed as they were and get the record.
"""

import os
import shutil

import numpy as np
import pytest
import zarr

from pipeline.jobs.info import summarize
from pipeline.jobs.reconstruct import JobIncomplete, ReconstructOptions, reconstruct
from pipeline.jobs.reconstruct_plan import MADE_FROM
from pipeline.stores.spike_store import SpikeMeta, SpikeStoreWriter, open_spike_store, store_identity
from tests.conftest import integrate_and_fire, smooth_rate
from tests.test_bad_input import assert_refused

FRAMES, SIDE, CHUNK = 128, 16, 16
LAST_CHUNK = os.path.join("spikes", "c", str(FRAMES // CHUNK - 1), "0", "0")  # frames 112..127
GAIN = 2.0  # fixed, as a store's recorded gain or --gain fixes it: the automatic gain would differ between recordings
TFP = ReconstructOptions(method="tfp", every=8, gain=GAIN)  # 11 output frames, centres 20..100; 92 and 100 read 112+


def write_recording(path, seed: int, *, old: bool = False) -> str:
    """A 128-frame 16x16 RGGB spike store in chunks of 16 frames; ``old``: as written before identities."""
    spikes = integrate_and_fire(smooth_rate(SIDE, SIDE, seed=seed), FRAMES, seed=seed)
    writer = SpikeStoreWriter(str(path), SpikeMeta(SIDE, SIDE, "rggb"), FRAMES, chunk_frames=CHUNK)
    writer.write(0, np.packbits(spikes, axis=-1, bitorder="little"))
    writer.finish(spike_count=int(spikes.sum()))
    if old:
        del zarr.open_group(str(path), mode="r+").attrs["identity"]
    return str(path)


def interrupted(store: str, out: str, options: ReconstructOptions, client) -> None:
    """Run a job whose input lacks its last chunk: it ends JobIncomplete with its other tasks committed;
    the chunk is put back after."""
    chunk = os.path.join(store, LAST_CHUNK)
    shutil.move(chunk, chunk + ".away")
    try:
        with pytest.raises(JobIncomplete, match="--resume"):
            reconstruct(store, out, options, client=client, progress=False)
    finally:
        shutil.move(chunk + ".away", chunk)
    group = zarr.open_group(out, mode="r")
    done = group["committed"][:]
    assert group.attrs["state"] == "writing" and 0 < done.sum() < done.size


def files(url: str) -> dict[str, bytes]:
    found = {}
    for folder, _, names in os.walk(url):
        for name in names:
            path = os.path.join(folder, name)
            with open(path, "rb") as handle:
                found[os.path.relpath(path, url)] = handle.read()
    return found


def cli_args(store, out, options: ReconstructOptions) -> list:
    args = ["reconstruct", store, out, "--resume", "--method", options.method, "--every", options.every,
            "--gain", options.gain, "--workers", 1]
    return args + (["--weights", options.weights] if options.weights else [])


def resumed_equals_clean(store: str, out: str, options: ReconstructOptions, client, tmp_path) -> None:
    clean = str(tmp_path / "clean.zarr")
    reconstruct(store, clean, options, client=client, progress=False)
    counts = reconstruct(store, out, ReconstructOptions(**{**options.__dict__, "resume": True}), client=client,
                         progress=False)
    assert counts["tasks_skipped"] > 0 and counts["tasks_run"] > 0
    got, want = files(out), files(clean)
    assert zarr.open_group(out, mode="r").attrs["state"] == "complete"
    assert {k for k in got if k.startswith(("video", "committed", "frames"))} == \
        {k for k in want if k.startswith(("video", "committed", "frames"))}
    for name, content in want.items():
        if name.startswith(("video", "committed", "frames")):
            assert got[name] == content, name


# --- (a) another recording at the input's path ---------------------------------------------------------------

@pytest.mark.parametrize("old", [False, True], ids=["store-with-identity", "store-from-before-identities"])
def test_resume_refuses_another_recording_at_the_same_path(client, cli, tmp_path, old):
    store, out = write_recording(tmp_path / "rec.zarr", seed=1, old=old), str(tmp_path / "out.zarr")
    interrupted(store, out, TFP, client)
    before = files(out)
    shutil.rmtree(store)
    write_recording(store, seed=2, old=old)  # another recording, same path, same shape and attributes

    result = cli(*cli_args(store, out, TFP))
    assert_refused(result, f"cannot resume {out}", "is not the recording it was made from",
                   "128 frames of 16x16", "--overwrite")
    assert files(out) == before  # untouched: still the interrupted output, not marked complete


@pytest.mark.parametrize("spelled", ["a copy", "a link", "file://"])
def test_resume_takes_the_same_recording_under_another_name(client, tmp_path, spelled):
    """A store moved or copied, a link to it, or its path as a ``file://`` URL: the same recording (its identity
    recorded), which ``--resume`` refused as "made with other parameters (source ...)"; it finishes with the bytes
    of an uninterrupted run. A store from before identities is still resumed on its path alone (above)."""
    store, out = write_recording(tmp_path / "rec.zarr", seed=1), str(tmp_path / "out.zarr")
    interrupted(store, out, TFP, client)
    elsewhere = str(tmp_path / "elsewhere.zarr")
    if spelled == "a copy":
        shutil.copytree(store, elsewhere)
    elif spelled == "a link":
        os.symlink(store, elsewhere)
    else:
        elsewhere = f"file://{store}"
    resumed_equals_clean(elsewhere, out, TFP, client, tmp_path)
    assert zarr.open_group(out, mode="r").attrs["source"] == store  # the record kept as it was made


def test_identity_names_the_recording_not_the_run(tmp_path):
    """The same recording written twice has the same identity (outputs stay bit-identical run to run), and a
    copy keeps it; another recording has another."""
    first, again = write_recording(tmp_path / "a.zarr", seed=1), write_recording(tmp_path / "b.zarr", seed=1)
    identity = open_spike_store(first).attrs["identity"]
    assert len(identity) == 64 and identity == open_spike_store(again).attrs["identity"]
    assert identity != open_spike_store(write_recording(tmp_path / "c.zarr", seed=2)).attrs["identity"]
    assert summarize(first)["identity"] == identity
    shutil.copytree(first, tmp_path / "copy.zarr")
    assert store_identity(open_spike_store(str(tmp_path / "copy.zarr"))) == identity
    old = write_recording(tmp_path / "old.zarr", seed=1, old=True)
    assert store_identity(open_spike_store(old)).startswith("metadata-")
    assert store_identity(open_spike_store(old)) != store_identity(open_spike_store(write_recording(
        tmp_path / "old2.zarr", seed=2, old=True)))


# --- (b) other weights at the weights' path ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def weights_files(tmp_path_factory):
    """The shipped lite weights, and a valid file of other weights (one tensor nudged)."""
    import torch

    from cscsr.weights.weights_io import default_weights, load_model, save_weights

    folder = tmp_path_factory.mktemp("weights")
    shipped = folder / "shipped.safetensors"
    shutil.copy(default_weights("lite"), shipped)
    model, _ = load_model(shipped)
    with torch.no_grad():
        next(iter(model.parameters())).add_(1e-3)
    other = folder / "other.safetensors"
    save_weights(model, other)
    return shipped, other


def network_job(weights) -> ReconstructOptions:
    return ReconstructOptions(method="cscsr", every=20, gain=GAIN, weights=str(weights))  # 5 frames; the last: 112+


def test_resume_refuses_other_weights_at_the_same_path(client, cli, tmp_path, weights_files):
    shipped, other = weights_files
    weights = tmp_path / "weights.safetensors"
    shutil.copy(shipped, weights)
    store, out = write_recording(tmp_path / "rec.zarr", seed=1), str(tmp_path / "out.zarr")
    options = network_job(weights)
    interrupted(store, out, options, client)
    before = files(out)
    shutil.copy(other, weights)  # other weights over the weights file

    result = cli(*cli_args(store, out, options))
    assert_refused(result, f"cannot resume {out}", f"its weights {weights} are not the ones it was made with")
    assert files(out) == before

    shutil.copy(shipped, weights)  # the weights it was made with, back: (c) for the network
    resumed_equals_clean(store, out, options, client, tmp_path)
    assert zarr.open_group(out, mode="r").attrs["weights_sha256"] == \
        zarr.open_group(str(tmp_path / "clean.zarr"), mode="r").attrs["weights_sha256"]


# --- (c) the same input and weights: resumed, the bytes of an uninterrupted run ---------------------------------

@pytest.mark.parametrize("old", [False, True], ids=["store-with-identity", "store-from-before-identities"])
def test_resume_with_the_same_recording_gives_the_clean_bytes(client, tmp_path, old):
    store, out = write_recording(tmp_path / "rec.zarr", seed=1, old=old), str(tmp_path / "out.zarr")
    interrupted(store, out, TFP, client)
    resumed_equals_clean(store, out, TFP, client, tmp_path)


def test_an_output_from_before_the_record_resumes_and_gets_it(client, cli, tmp_path):
    """Outputs made before this check record no identity: resumed on the paths alone (as before), and the
    record is added, so that a later resume onto another recording is refused."""
    store, out = write_recording(tmp_path / "rec.zarr", seed=1), str(tmp_path / "out.zarr")
    interrupted(store, out, TFP, client)
    group = zarr.open_group(out, mode="r+")
    recorded = {k: group.attrs[k] for k in MADE_FROM}
    for key in MADE_FROM:
        del group.attrs[key]

    shutil.move(os.path.join(store, LAST_CHUNK), tmp_path / "away")  # the first resume is cut off again
    with pytest.raises(JobIncomplete):
        reconstruct(store, out, ReconstructOptions(**{**TFP.__dict__, "resume": True}), client=client, progress=False)
    shutil.move(tmp_path / "away", os.path.join(store, LAST_CHUNK))
    assert {k: zarr.open_group(out, mode="r").attrs[k] for k in MADE_FROM} == recorded  # adopted

    shutil.rmtree(store)
    write_recording(store, seed=2)
    assert_refused(cli(*cli_args(store, out, TFP)), "is not the recording it was made from")


def test_a_long_lived_worker_reloads_weights_replaced_at_the_same_path(client, tmp_path, weights_files):
    """Workers keep a loaded model per weights file: after other weights are copied over the file, the next
    job on the same workers must run the new weights (the model is keyed by the file's SHA-256), giving what
    a fresh cluster gives, never the old model under the new file's record."""
    shipped, other = weights_files
    weights = tmp_path / "weights.safetensors"
    store = write_recording(tmp_path / "rec.zarr", seed=1)
    shutil.copy(other, weights)
    fresh = str(tmp_path / "fresh.zarr")
    reconstruct(store, fresh, network_job(weights), workers=1, progress=False)  # a cluster that never saw shipped
    shutil.copy(shipped, weights)
    reconstruct(store, str(tmp_path / "first.zarr"), network_job(weights), client=client, progress=False)
    shutil.copy(other, weights)  # other weights over the file the workers have loaded
    second = str(tmp_path / "second.zarr")
    reconstruct(store, second, network_job(weights), client=client, progress=False)
    assert zarr.open_group(second)["video"][:].tobytes() == zarr.open_group(fresh)["video"][:].tobytes()
    assert zarr.open_group(second)["video"][:].tobytes() != \
        zarr.open_group(str(tmp_path / "first.zarr"))["video"][:].tobytes()
