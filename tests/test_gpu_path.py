"""The GPU workers' data path, run on the CPU: packed bits in, uint8 out, several tasks in flight.

- The device-side steps (``cscsr.inference.device_steps``) give the numpy steps' bytes, and ``many()`` gives the
  bytes of the path before them (numpy unpacking, the network on float32 spikes, numpy exposure).
- The device lock: one call on the device at a time, released when a call raises.
- Where the network runs decides the default weights, the tile and the windows per pass.
- On a worker that advertises a GPU and runs ``GPU_TASKS_IN_FLIGHT`` tasks at once: tasks overlap,
  device passes do not; a task whose device pass raises is named in the job's error, every other frame
  is committed, and ``--resume`` finishes to a clean run's bytes; a killed job resumes to them too.
"""

import contextlib
import dataclasses
import logging
import os
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import torch
from distributed import Client, Nanny, Scheduler, SpecCluster, get_task_stream

from cscsr.inference.device_steps import expose_uint8, unpack_bits
from cscsr.inference.reconstructor import load_reconstructor
from pipeline.compute.cluster import GPU, GPU_SHARE, GPU_TASKS_IN_FLIGHT
from pipeline.compute.hold import hold_environment
from pipeline.jobs.reconstruct import (JobIncomplete, Placement, ReconstructOptions, placed, reconstruct, reconstructor,
                                  sized)
from pipeline.jobs.reconstruct_plan import DEFAULT_TILE, GPU_BATCH
from pipeline.stores.spike_store import open_spike_store
from stages.capture.bits import pack_rows, unpack_rows
from stages.reconstruction.colour import expose
from stages.errors import InputError
from stages.reconstruction.methods import Window
from stages.reconstruction.tiles import device_tile, tile_grid
from tests.test_gpu_workers import method_records
from tests.test_gpu_workers import wide  # noqa: F401 - the module's recording fixture, LR 32x96 RGGB
from tests.conftest import committed_tasks, kill_mid_job
from tests.test_simulate import chunk_files

LITE = ReconstructOptions(method="cscsr", weights="lite", every=10, tile=32)  # 6 frames x 3 tiles: 4 GPU tasks
BIN = os.path.dirname(sys.executable)


# --- the device-side steps ------------------------------------------------------------------

def test_unpacking_on_the_device_is_numpys():
    rng = np.random.default_rng(0)
    for width in (1, 7, 8, 9, 96, 101):
        bits = (rng.random((2, 5, 3, width)) < 0.4).astype(np.uint8)
        packed = pack_rows(bits)
        assert np.array_equal(unpack_bits(torch.from_numpy(packed), width).numpy(), unpack_rows(packed, width))
        assert np.array_equal(unpack_rows(packed, width), bits)


def test_exposure_on_the_device_is_numpys_to_the_byte():
    rng = np.random.default_rng(1)
    rate = rng.normal(0.3, 0.4, (64, 64, 3)).astype(np.float32)  # negatives and values over 1 too
    rate[0, :, 0] = (np.arange(64) + 0.5) / 255  # exactly half-way between two levels at gain 1: ties to even
    for gain in (1.0, 0.37, 3.3, 255.0, 1e5):
        assert np.array_equal(expose_uint8(torch.from_numpy(rate.copy()), gain).numpy(), expose(rate, gain)), gain
    rate[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="1 of 12288 values of the exposed image are not finite"):
        expose_uint8(torch.from_numpy(rate), 1.0)
    with pytest.raises(ValueError, match="gain"):
        expose_uint8(torch.from_numpy(rate), float("inf"))


def windows_of(store_url: str, tile: int, centres=(20, 30)) -> list[list[Window]]:
    """The windows the pipeline's tasks build for ``tile`` (read region halo included), per tile."""
    store = open_spike_store(store_url)
    meta = store.meta
    grid = tile_grid(meta.height, meta.width, tile, 32)
    return [[Window(store.read(c - 20, c + 21)[:, t.ry0:t.ry1, t.rx0 // 8:-(-t.rx1 // 8)], t.rx1 - t.rx0, meta.cfa,
                    meta.reset, meta.gain, 4) for c in centres] for row in grid for t in row]


def old_path(network, windows: list[Window]) -> list[np.ndarray]:
    """What ``many()`` did before the device-side path: numpy unpacking, float32 spikes to the device, the
    network, the float32 image back, numpy exposure."""
    first = windows[0]
    spikes = np.stack([unpack_rows(w.packed, w.width) for w in windows])
    torch.set_num_threads(1)
    with torch.inference_mode(), network._autocast():
        x = torch.from_numpy(spikes).to(network.device, torch.float32)
        views = range(8) if network.self_ensemble else (0,)
        rate = sum(network._seen_under(k, x, first) for k in views) / len(views)
        rate = rate.permute(0, 2, 3, 1).float().cpu().numpy()
    return [expose(r, first.gain) for r in rate]


def test_the_device_path_gives_the_old_paths_bytes(wide):  # noqa: F811
    """For the tiles that both paths use (tile 32: reads of 64 and 96 columns; tile 96: the whole frame)."""
    network = load_reconstructor("lite", "cpu")
    threads = torch.get_num_threads()
    try:
        for tile in (32, 96):
            for windows in windows_of(wide, tile):
                new = network.many(windows)
                assert [i.shape for i in new] == [(128, 4 * windows[0].width, 3)] * 2
                assert all(np.array_equal(a, b) for a, b in zip(new, old_path(network, windows))), tile
        ensemble = load_reconstructor("lite", "cpu", self_ensemble=True)
        windows = windows_of(wide, 32, centres=(20,))[0]
        assert np.array_equal(ensemble.many(windows)[0], old_path(ensemble, windows)[0])
    finally:
        torch.set_num_threads(threads)


def test_the_device_path_gives_the_old_paths_bytes_in_bf16(wide):  # noqa: F811
    """bf16 (autocast) on two 16x16 windows (a corner of the first tile's): a CPU without native bfloat16
    emulates it at about 6 ms a pixel of a window, and the arithmetic is the same at any size."""
    network = load_reconstructor("lite", "cpu", precision="bf16")
    windows = [dataclasses.replace(w, packed=w.packed[:, :16, :2], width=16) for w in windows_of(wide, 32)[0]]
    threads = torch.get_num_threads()
    try:
        new = network.many(windows)
        assert [i.shape for i in new] == [(64, 64, 3)] * 2
        assert all(np.array_equal(a, b) for a, b in zip(new, old_path(network, windows)))
        assert not np.array_equal(new[0], load_reconstructor("lite", "cpu").many(windows)[0])  # bf16 is not fp32
    finally:
        torch.set_num_threads(threads)


def test_one_device_pass_at_a_time_and_the_lock_survives_an_error(wide):  # noqa: F811
    network = load_reconstructor("lite", "cpu")
    windows = windows_of(wide, 32, centres=(20,))[0]
    inside, most, calls = [0], [0], [0]
    real = network.device_images

    def watched(packed, window):
        inside[0] += 1
        most[0] = max(most[0], inside[0])
        calls[0] += 1
        try:
            time.sleep(0.05)
            if calls[0] == 2:
                raise RuntimeError("device fault")
            return real(packed, window)
        finally:
            inside[0] -= 1

    network.device_images = watched
    errors = []

    def call():
        try:
            network.many(windows)
        except RuntimeError as error:
            errors.append(str(error))

    threads = [threading.Thread(target=call) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=120)
    assert not any(thread.is_alive() for thread in threads), "a call waits for ever on the device lock"
    assert most[0] == 1 and calls[0] == 4 and errors == ["device fault"]


# --- what depends on where the network runs -------------------------------------------------

def test_default_weights_tile_and_passes_by_placement():
    network = ReconstructOptions(method="cscsr")
    gpu, cpu, unknown = Placement(True, 80 * 2**30), Placement(False, None), Placement(True, None)
    assert placed(network, gpu, {}).weights == "full" and placed(network, cpu, {}).weights == "lite"
    assert placed(network, gpu, {"weights": "/w/old.safetensors"}).weights == "/w/old.safetensors"  # a resume
    assert placed(ReconstructOptions(method="cscsr", weights="lite"), gpu, {}).weights == "lite"
    assert placed(ReconstructOptions(method="tfp"), gpu, {}).weights is None
    full = reconstructor("cscsr", "full", device="cpu")  # halo 32, configuration "full"
    whole = sized(network, gpu, full, (1000, 1000), {})
    assert (whole.tile, whole.gpu_batch) == (1000, 2)  # the whole frame, 2 windows of 24.8 GiB in 64 GiB (fp32)
    bf16 = sized(ReconstructOptions(method="cscsr", precision="bf16"), gpu, full, (1000, 1000), {})
    assert (bf16.tile, bf16.gpu_batch) == (1000, 4)  # 15.5 GiB a window
    small = sized(network, Placement(True, 16 * 2**30), full, (1000, 1000), {})
    assert small.tile == 648 and small.gpu_batch == 1  # (648 + 64)^2 px x 26.6 kB <= 12.8 GiB
    assert [sized(network, where, full, (1000, 1000), {}).tile for where in (cpu, unknown)] == [DEFAULT_TILE] * 2
    assert sized(network, unknown, full, (1000, 1000), {}).gpu_batch == GPU_BATCH
    assert sized(network, gpu, full, (1000, 1000), {"tile_lr": 128}).tile == 128  # a resume keeps its tile
    assert sized(ReconstructOptions(method="cscsr", tile=64, gpu_batch=2), gpu, full, (1000, 1000), {}).tile == 64
    assert device_tile(999, 600, 32, 1e12, 1.0, 16) == (1000, 16)  # rounded up to a multiple of 8
    assert device_tile(1000, 1000, 32, 72.0 * 72, 1.0, 16) == (8, 1)  # the smallest tile: 8 + 2 halos of 32
    with pytest.raises(InputError, match="holds no tile"):
        device_tile(1000, 1000, 32, 71.0 * 71, 1.0, 16)


# --- several tasks in flight on one GPU worker -----------------------------------------------

@contextlib.contextmanager
def gpu_worker(env: dict | None = None):
    """A scheduler and one worker process that advertises a GPU, with the GPU worker's threads."""
    spec = {"gpu": {"cls": Nanny, "options": {"nthreads": GPU_TASKS_IN_FLIGHT, "resources": {GPU: 1},
                                              "env": env or {}}}}
    with SpecCluster(workers=spec, scheduler={"cls": Scheduler, "options": {"dashboard_address": ":0"}},
                     silence_logs=logging.ERROR) as cluster, Client(cluster) as client:
        client.wait_for_workers(1)
        yield client


def _faulty_device(fail_on_call: int) -> None:
    """Run on the worker: the loaded network's device pass records when it runs, and raises on one call."""
    import pipeline.jobs.reconstruct_tasks as module

    real = module.reconstructor
    log = module._device_log = []

    def faulty(*args, **kwargs):
        network = real(*args, **kwargs)
        if getattr(network, "_real_device_images", None) is None:
            network._real_device_images = network.device_images

            def device_images(packed, window):
                start = time.monotonic()
                try:
                    if len(log) + 1 == fail_on_call:
                        raise RuntimeError("device fault in this pass")
                    return network._real_device_images(packed, window)
                finally:
                    log.append((start, time.monotonic()))

            network.device_images = device_images
        return network

    module.reconstructor = faulty


def _device_passes() -> list:
    import pipeline.jobs.reconstruct_tasks as module

    return module._device_log


@pytest.fixture(scope="module")
def clean_gpu_run(wide, tmp_path_factory):  # noqa: F811
    out = str(tmp_path_factory.mktemp("gpu-clean") / "clean.zarr")
    with gpu_worker() as client:
        reconstruct(wide, out, LITE, client=client, progress=False)
    return chunk_files(out)


def test_tasks_overlap_device_passes_do_not_and_a_failed_pass_is_named(wide, clean_gpu_run, tmp_path):  # noqa: F811
    out = str(tmp_path / "out.zarr")
    with gpu_worker() as client:
        client.run(_faulty_device, 2)
        start = time.monotonic()
        with get_task_stream(client) as stream, pytest.raises(JobIncomplete) as failed:
            reconstruct(wide, out, LITE, client=client, progress=False)
        assert time.monotonic() - start < 300
        passes = sorted(next(iter(client.run(_device_passes).values())))
        tasks = sorted((r["startstops"][0]["start"], r["startstops"][-1]["stop"])
                       for r in method_records(stream.data))
    assert GPU_SHARE * GPU_TASKS_IN_FLIGHT == 1 and len(tasks) == 4
    assert len(passes) in (5, 6)  # a pass per tile on the CPU (tiles are joined on a GPU): 6, less the failed task's rest
    assert any(b[0] < a[1] for a, b in zip(tasks, tasks[1:])), "no two tasks were in flight together"
    assert all(b[0] >= a[1] for a, b in zip(passes, passes[1:])), "two device passes overlapped"
    error = str(failed.value)
    assert "device fault in this pass" in error and "--resume" in error
    missing = sorted(failed.value.failed)
    assert missing in ([0, 1, 2, 3], [4, 5])  # one task's frames (4 frames of two tiles, or the last 2 of one)
    reconstruct(wide, out, LITE.__class__(**{**LITE.__dict__, "resume": True}), workers=1, progress=False)
    assert chunk_files(out) == clean_gpu_run


def test_a_killed_job_on_a_gpu_worker_resumes_to_the_clean_bytes(wide, clean_gpu_run, tmp_path):  # noqa: F811
    release, out = tmp_path / "release", str(tmp_path / "killed.zarr")
    with gpu_worker(hold_environment(1, release)) as client:  # every task after the first holds
        address = client.scheduler.address
        command = [f"{BIN}/cscsr", "reconstruct", wide, out, "--method", "cscsr", "--weights", "lite", "--every", "10",
                   "--tile", "32", "--scheduler", address]
        kill_mid_job(command, lambda: committed_tasks(out) >= 1)  # mid-way: its other tasks are held on the worker
        release.touch()
        done = subprocess.run([*command, "--resume"], capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
    assert chunk_files(out) == clean_gpu_run


def test_fast_gpu_is_ignored_on_the_cpu_and_refused_without_a_network(wide, tmp_path):  # noqa: F811
    plain, fast = load_reconstructor("lite", "cpu"), load_reconstructor("lite", "cpu", fast_gpu=True)
    assert fast.forward is fast.model and not fast.model.channels_last  # no compile, no NHWC: the CPU's bytes
    windows = windows_of(wide, 32, centres=(20,))[0]
    assert np.array_equal(plain.many(windows)[0], fast.many(windows)[0])
    for options in (dict(method="tfp"), dict(method="cscsr", backend="onnx")):
        with pytest.raises(InputError, match="--fast-gpu is for the network on torch"):
            ReconstructOptions(fast_gpu=True, **options).check()
    with pytest.raises(InputError, match="--fast-gpu"):
        ReconstructOptions(method="cscsr", fast_gpu="yes").check()
    out = tmp_path / "fast.zarr"
    reconstruct(wide, str(out), ReconstructOptions(method="tfp", every=40, tile=32), workers=1, progress=False)
    import zarr

    assert zarr.open_group(str(out), mode="r").attrs["fast_gpu"] is None  # recorded; null for classic methods
