"""The GPU lease script (benchmarks/gpu_lease.py), dry-run on the CPU with tiny settings."""

import json
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from cscsr.weights.weights_io import read_metadata
from pipeline.jobs.reconstruct_plan import DEFAULT_TILE

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "gpu_lease.py"
LEASE_FILES, LEASE_FILE_BYTES = 8, 16 * 2**20  # what may come back from a lease


def lease(*args) -> str:
    run = subprocess.run([sys.executable, str(SCRIPT), *map(str, args)], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    return run.stdout


def lease_here(monkeypatch, capsys, *args) -> str:
    """``lease(*args)`` in this process, the script run as ``python gpu_lease.py ARGS`` runs it (a failure raises) but
    without a new interpreter importing torch again: what it printed."""
    monkeypatch.syspath_prepend(str(SCRIPT.parent))  # where the script's own imports come from, as for the command
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), *map(str, args)])
    capsys.readouterr()
    runpy.run_path(str(SCRIPT), run_name="__main__")
    return capsys.readouterr().out


def test_pack_reencodes_pictures_and_keeps_sequences_whole(tmp_path):
    from cscsr.training.frame_motion import group_sequences
    from cscsr.training.training_data import picture_files

    rng = np.random.default_rng(0)
    (tmp_path / "stills").mkdir()
    iio.imwrite(tmp_path / "stills" / "big.png", rng.integers(0, 255, (800, 600, 3), dtype=np.uint8))
    for i in range(7):
        (tmp_path / "clips" / "walk").mkdir(parents=True, exist_ok=True)
        iio.imwrite(tmp_path / "clips" / "walk" / f"{i:05d}.png", rng.integers(0, 255, (240, 320, 3), dtype=np.uint8))
    report = json.loads(lease("pack", tmp_path / "stills", "--sequences", tmp_path / "clips", "--dest",
                              tmp_path / "packed", "--short-side", 300))
    assert report["pictures"] == 1 + 7
    assert iio.imread(tmp_path / "packed" / "stills" / "big.jpg").shape == (400, 300, 3)  # short side 300
    sources = group_sequences(picture_files([tmp_path / "packed"]))
    frames, still = sources  # the frames (sorted first: clips/ before stills/) are still a sequence, in order
    assert still.endswith("big.jpg") and [n.rsplit("/", 1)[-1] for n in frames] == [f"{i:05d}.jpg" for i in range(7)]


def test_check_and_two_training_slices_fit_what_a_lease_brings_back(tmp_path, monkeypatch, capsys):
    """The lease's commands on one machine (run in this process: a slice goes on from what the one before left in
    --run), then a fresh machine's (a command of its own) from the portable checkpoint's parts alone."""
    out, run = tmp_path / "out", tmp_path / "run"
    lease_here(monkeypatch, capsys, "check", "--tiny", "--out", out)
    check = json.loads((out / "check.json").read_text())
    assert check["smoke"]["steps"] == 4 and check["synthesis"]["device_clips_per_s"] > 0

    first = lease_here(monkeypatch, capsys, "train", "--tiny", "--out", out, "--run", run)
    assert "starting" in first and (run / "checkpoint.safetensors").exists()
    second = lease_here(monkeypatch, capsys, "train", "--tiny", "--out", out, "--run", run)  # the next resumes
    assert "resuming" in second
    metadata = read_metadata(out / "cscsr-lite.safetensors")
    assert metadata["storage"] == "float16" and metadata["steps"] == "8"
    steps = [json.loads(line)["step"] for line in (out / "log.jsonl").read_text().splitlines()]
    assert steps == [2, 4, 6, 8]
    files = [f for f in out.rglob("*") if f.is_file()]
    assert len(files) <= LEASE_FILES and all(f.stat().st_size <= LEASE_FILE_BYTES for f in files)

    # what came back goes on on a fresh machine: the portable checkpoint's parts carried into an empty run folder
    parts = sorted(out.glob("checkpoint.part-*.safetensors"))
    assert [p.name for p in parts] == ["checkpoint.part-1-of-1.safetensors"]  # lite: 8 MB with fp16 weights
    fresh = tmp_path / "fresh"
    fresh.mkdir()
    shutil.copy(parts[0], fresh)
    third = lease("train", "--tiny", "--out", tmp_path / "out3", "--run", fresh, "--steps", 10)
    assert "resuming" in third and "resumed at step 8 from the portable checkpoint" in third
    assert read_metadata(tmp_path / "out3" / "cscsr-lite.safetensors")["steps"] == "10"
    steps = [json.loads(line)["step"] for line in (tmp_path / "out3" / "log.jsonl").read_text().splitlines()]
    assert steps == [10]


def test_prove_runs_every_step_on_the_cpu_and_keeps_what_each_measured(tmp_path, monkeypatch, capsys):
    """The lease's one command (issue #46), tiny and on the CPU, `lite` in fp32 (bf16 on a CPU without native
    bfloat16 is emulated, slowly; its device path is tested in test_gpu_path.py): there the device path is the
    CPU path, so it gives the CPU path's bytes exactly; the pipeline step's figures land in prove.json and
    gpu_pipeline.json; a step that would not fit the budget is skipped. (The orchestrator runs in this process; each
    step, as on a lease, in a process of its own.)"""
    out = tmp_path / "out"
    lease_here(monkeypatch, capsys, "prove", "--device", "cpu", "--tiny", "--out", out, "--configs", "lite",
               "--precisions", "fp32")
    report = json.loads((out / "prove.json").read_text())
    assert {name: step["status"] for name, step in report["steps"].items()} == {
        "smoke": "ok", "smoke-fast-gpu": "ok", "pipeline-lite-fp32": "ok"}  # the steps with lite in fp32
    (run,) = report["steps"]["smoke"]["result"]["runs"]
    assert (run["config"], run["precision"]) == ("lite", "fp32")
    assert run["ok"] and run["repeatable"] and run["against_host_path"]["equal_bytes"], run
    assert run["against_cpu_path"]["equal_bytes"] and run["within_tolerance_of_cpu"], run
    (fast,) = report["steps"]["smoke-fast-gpu"]["result"]["runs"]
    assert fast["ok"] and fast["against_eager_device_path"]["equal_bytes"]  # a CPU ignores --fast-gpu
    (pipeline,) = report["steps"]["pipeline-lite-fp32"]["result"]
    assert (pipeline["config"], pipeline["precision"], pipeline["tile"]) == ("lite", "fp32", DEFAULT_TILE)  # CPU
    assert pipeline["pipeline_frames_per_second"] > 0 and pipeline["forward_frames_per_second"] > 0
    assert pipeline["worker_gpu_peak_mib"] is None  # no CUDA in the worker
    (measured,) = json.loads((out / "gpu_pipeline.json").read_text())["runs"]
    assert measured["pipeline_frames_per_second"] == pipeline["pipeline_frames_per_second"]
    assert list(report["goals"]) == ["lite-fp32: pipeline / forward >= 0.85"]
    files = [f for f in out.rglob("*") if f.is_file()]
    assert len(files) <= LEASE_FILES and all(f.stat().st_size <= LEASE_FILE_BYTES for f in files)

    skipped = tmp_path / "skipped"
    lease_here(monkeypatch, capsys, "prove", "--device", "cpu", "--tiny", "--out", skipped, "--configs", "lite",
               "--precisions", "fp32", "--only", "pipeline-lite-fp32", "--budget", 60)
    report = json.loads((skipped / "prove.json").read_text())
    assert report["steps"]["pipeline-lite-fp32"]["status"] == "skipped"  # needs 80 s or more of the 60
    assert not (skipped / "gpu_pipeline.json").exists()
    assert "=== recording" not in (skipped / "prove.log").read_text()  # nor its recording simulated for nothing


def test_prove_measures_the_network_s_compile_bf16_and_convolutions_first(tmp_path, monkeypatch, capsys):
    """#53's measurements, dry-run on the CPU (tiny; the compile with torch.compile's eager backend): full's compile
    first, with the profiler's top kernels eager and compiled; bf16 against fp32; the convolution micro-benchmarks.
    (The orchestrator runs in this process; each step in a process of its own.)"""
    out = tmp_path / "out"
    lease_here(monkeypatch, capsys, "prove", "--device", "cpu", "--tiny", "--out", out, "--only",
               "compile-full,bf16-1000,micro")
    report = json.loads((out / "prove.json").read_text())
    assert list(report["steps"]) == ["compile-full", "bf16-1000", "micro"]  # the compile first
    assert all(step["status"] == "ok" for step in report["steps"].values()), report["steps"]
    compiled = report["steps"]["compile-full"]["result"]
    assert compiled["compile_and_first_pass_s"] > 0 and compiled["largest_difference"] == 0  # eager backend: exact
    assert 0 < len(compiled["top25_eager"]) <= 25 and 0 < len(compiled["top25_compiled"]) <= 25
    (bf16,) = report["steps"]["bf16-1000"]["result"]["runs"]  # lite only in the dry run
    assert bf16["psnr_db"] >= 40 and bf16["mean_abs_levels"] <= 1
    cases = report["steps"]["micro"]["result"]["cases"]
    assert set(cases) == {"conv 96->96 NCHW", "conv 96->96 NHWC", "conv3d 50->50 NDHWC", "conv3d 56->56 NDHWC",
                          "conv 101->50 NHWC", "conv 104->56 NHWC"} and all(c["ms"] > 0 for c in cases.values())


def test_a_compiled_forward_is_kept_as_it_is():
    """--fast-gpu on a GPU: the reconstructor is given the torch.compile'd model. The first lease found every
    --fast-gpu load failing ('CSCSR does not support len()': a compiled module's truth asks the model's len)."""
    import torch

    from cscsr.inference.reconstructor import NetworkReconstructor, load_reconstructor

    network = load_reconstructor("lite", "cpu")
    compiled = torch.compile(network.model)  # lazy: nothing compiles until it is called
    assert NetworkReconstructor(network.model, network.device, network.weights, forward=compiled).forward is compiled
    assert network.forward is network.model
