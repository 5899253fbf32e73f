"""The Python API (``from cscsr import ingest, simulate, reconstruct, evaluate``) on a real LocalCluster:
what each function returns, where it runs without a client (Dask's own configuration), and that
``import cscsr`` alone leaves the pipeline and Dask unimported."""

import subprocess
import sys
from dataclasses import FrozenInstanceError

import cv2
import dask
from dask.utils import key_split
import imageio.v3 as iio
import numpy as np
import pytest
from distributed import get_task_stream

from cscsr import Written, evaluate, ingest, reconstruct, simulate
from pipeline.stores.video_store import open_video_store
from stages.errors import InputError
from tests.conftest import integrate_and_fire, smooth_rate, write_dat
from tests.test_simulate import picture

HEIGHT, WIDTH, FRAMES = 16, 24, 82


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A static RGGB scene of known firing rates: the .dat path, its spikes and the rates."""
    rate = smooth_rate(HEIGHT, WIDTH)
    bits = integrate_and_fire(rate, FRAMES)
    path = tmp_path_factory.mktemp("capture") / "scene.dat"
    write_dat(path, bits)
    return str(path), bits, rate


def test_ingest_then_reconstruct_with_a_given_client(capture, client, tmp_path):
    src, bits, rate = capture
    store, out = str(tmp_path / "spikes.zarr"), str(tmp_path / "video.zarr")

    ingested = ingest(src, store, height=HEIGHT, width=WIDTH, cfa="rggb", client=client)
    assert isinstance(ingested, Written) and ingested.url == store
    assert ingested.counts == {"frames": FRAMES, "spikes": int(bits.sum())}
    assert (ingested.attrs["height"], ingested.attrs["width"], ingested.attrs["cfa"]) == (HEIGHT, WIDTH, "rggb")
    assert ingested.attrs["spike_count"] == int(bits.sum())

    with get_task_stream(client) as stream:
        made = reconstruct(store, out, method="tfp", every=41, gain=1.0, client=client)
    assert made.url == out and made.counts == {"frames": 2, "tasks_run": 2, "tasks_skipped": 0}
    assert made.attrs["method"] == "tfp" and made.attrs["state"] == "complete" and made.attrs["every"] == 41
    assert sum(key_split(task["key"]) in ("tfp", "tfi") for task in stream.data) == 2  # ran on this cluster

    video = open_video_store(out)["video"][:]
    assert video.shape == (2, 4 * HEIGHT, 4 * WIDTH, 3) and video.dtype == np.uint8
    # a static scene: both frames show the rates it fired at (window means, demosaicked, upsampled)
    grey = video.astype(np.float64).mean(axis=(0, 3))
    expected = cv2.resize(rate, (4 * WIDTH, 4 * HEIGHT), interpolation=cv2.INTER_LINEAR)
    assert np.corrcoef(grey.ravel(), expected.ravel())[0, 1] > 0.9
    with pytest.raises(FrozenInstanceError):
        made.url = "elsewhere"


def test_bad_options_are_refused_before_any_output(capture, client, tmp_path):
    src, _, _ = capture
    with pytest.raises(TypeError, match="unknown option 'colour'.*height"):
        ingest(src, str(tmp_path / "a.zarr"), height=HEIGHT, width=WIDTH, colour="rggb")
    # every keyword named, the function's own too (workers, dry_run, ... were left out)
    with pytest.raises(TypeError, match=r"^reconstruct\(\) got an unknown option 'worker': expected some of client, "
                                        r"workers, scheduler, progress, dry_run, method, "):
        reconstruct(src, str(tmp_path / "a.zarr"), worker=2)
    with pytest.raises(TypeError, match=r"^ingest\(\) got an unknown option 'dryrun': expected .*, dry_run, height"):
        ingest(src, str(tmp_path / "a.zarr"), dryrun=True)
    with pytest.raises(InputError, match="unknown CFA .rgbw."):
        ingest(src, str(tmp_path / "b.zarr"), height=HEIGHT, width=WIDTH, cfa="rgbw")
    store = str(tmp_path / "spikes.zarr")
    ingest(src, store, height=HEIGHT, width=WIDTH, cfa="rggb")
    with pytest.raises(InputError, match="method"):
        reconstruct(store, str(tmp_path / "c.zarr"), method="magic", client=client)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["spikes.zarr"]


@pytest.mark.parametrize("how", ["environment", "dask-config"])
def test_without_a_client_dask_configuration_names_the_scheduler(capture, client, tmp_path, monkeypatch, how):
    """DASK_SCHEDULER_ADDRESS, or scheduler-address in Dask's configuration: the job's tasks run on that
    scheduler's workers (its task stream records them), not on a local cluster of its own."""
    src, _, _ = capture
    store = str(tmp_path / "spikes.zarr")
    ingest(src, store, height=HEIGHT, width=WIDTH, cfa="rggb")
    address = client.scheduler.address
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    if how == "environment":
        monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", address)
    with dask.config.set({"scheduler-address": address} if how == "dask-config" else {}), \
            get_task_stream(client) as stream:
        made = reconstruct(store, str(tmp_path / "video.zarr"), method="tfi", every=41)
    assert made.counts["tasks_run"] == 2
    ran = [task for task in stream.data if key_split(task["key"]) in ("tfp", "tfi")]
    assert len(ran) == 2 and {task["worker"] for task in ran} <= set(client.scheduler_info()["workers"])


@pytest.mark.parametrize("how", ["environment", "dask-config"])
def test_workers_and_a_scheduler_the_configuration_names_contradict(capture, cli, tmp_path, monkeypatch, how):
    """The configuration's scheduler counts as ``--scheduler``, which ``--workers`` contradicts: it won, silently
    (``--workers 1`` ran on, or failed to reach, that scheduler). One line, nothing made, CLI and API alike."""
    src, _, _ = capture
    address, by = "tcp://127.0.0.1:9", "DASK_SCHEDULER_ADDRESS" if how == "environment" else "scheduler-address"
    monkeypatch.delenv("DASK_SCHEDULER_ADDRESS", raising=False)
    if how == "environment":
        monkeypatch.setenv("DASK_SCHEDULER_ADDRESS", address)
    said = f"workers.1 and the scheduler .*{by}.* names \\({address}\\) contradict each other"
    with dask.config.set({"scheduler-address": address} if how == "dask-config" else {}):
        with pytest.raises(InputError, match=said):
            ingest(src, str(tmp_path / "a.zarr"), height=HEIGHT, width=WIDTH, workers=1)
        result = cli("reconstruct", str(tmp_path / "a.zarr"), str(tmp_path / "b.zarr"), "--workers", "1")
    assert result.exit_code == 1 and "contradict each other" in result.stderr and not list(tmp_path.iterdir())


def test_simulate_and_evaluate_with_a_given_client(client, tmp_path):
    iio.imwrite(tmp_path / "scene.png", picture("astronaut", 64))
    store = str(tmp_path / "sim.zarr")
    with get_task_stream(client) as stream:
        made = simulate(str(tmp_path / "scene.png"), store, scale=4, frames=41, motion="static", client=client)
    assert made.url == store and made.counts["frames"] == 41 and made.counts["spikes"] == made.attrs["spike_count"] > 0
    assert (made.attrs["height"], made.attrs["width"], made.attrs["scale"]) == (16, 16, 4)
    assert any(key_split(task["key"]) == "to-spikes" for task in stream.data)  # simulated on the given cluster

    scored = evaluate(store, "tfp,tfi", str(tmp_path / "evaluation"), client=client)
    assert scored.url == str(tmp_path / "evaluation") and [row["method"] for row in scored.rows] == ["tfp", "tfi"]
    assert all(row["frames"] == 1 and 10 < row["psnr"] < 60 and 0 < row["ssim"] <= 1 for row in scored.rows)
    assert {"metrics.csv", "summary.csv", "comparison.png"} <= {p.name for p in (tmp_path / "evaluation").iterdir()}
    assert scored.counts == {"methods": 2, "videos": 0}

    # numpy numbers, what arithmetic on arrays gives, are the numbers they hold: they passed the checks and then
    # failed to be recorded ("Object of type int64 is not JSON serializable")
    again = simulate(str(tmp_path / "scene.png"), str(tmp_path / "numpy.zarr"), scale=np.int64(4),
                     frames=np.int64(41), motion="static", seed=np.int64(0), client=client)
    assert again.attrs == {**made.attrs, "source": again.attrs["source"]} and type(again.attrs["scale"]) is int
    video = reconstruct(store, str(tmp_path / "numpy-video.zarr"), method="tfp", every=np.int64(41),
                        region=tuple(np.array([0, 8, 0, 16])), client=client)
    assert video.attrs["every"] == 41 and video.attrs["region"] == [0, 8, 0, 16]


def test_a_client_and_workers_or_a_scheduler_contradict(client, tmp_path):
    """``client=`` with ``workers=`` or ``scheduler=``: ``reconstruct`` and ``evaluate`` ran on the client, the
    others silently ignored (a dead address included), and ``simulate`` named a ``--scheduler`` nobody gave."""
    for job, args in ((simulate, ("scene.png", str(tmp_path / "s.zarr"))),
                      (reconstruct, ("spikes.zarr", str(tmp_path / "v.zarr"))),
                      (evaluate, ("spikes.zarr", "tfp", str(tmp_path / "e")))):
        with pytest.raises(InputError, match=r"\(\): client= and workers=2 contradict each other"):
            job(*args, client=client, workers=2)
        with pytest.raises(InputError, match=r"client= and scheduler='tcp://127.0.0.1:1' contradict each other"):
            job(*args, client=client, scheduler="tcp://127.0.0.1:1")
        with pytest.raises(InputError, match=r"\(\): scheduler is empty"):
            job(*args, scheduler="")
    with pytest.raises(TypeError, match="unknown option 'every': expected some of weights, client"):
        evaluate("spikes.zarr", "tfp", str(tmp_path / "e"), every=10)
    assert not list(tmp_path.iterdir())


def test_import_cscsr_imports_neither_the_pipeline_nor_dask():
    code = ("import sys, cscsr; loaded = sorted(m for m in sys.modules if m.split('.')[0] in "
            "('pipeline', 'dask', 'distributed')); print(loaded); "
            "from cscsr import reconstruct; print(reconstruct.__module__)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.split("\n")[:2] == ["[]", "pipeline.api"]
