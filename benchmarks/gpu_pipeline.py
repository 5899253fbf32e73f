"""The CSCSR pipeline on one GPU worker: how busy it keeps the device (issue #35).

Two modes, both on a simulated RGGB spike recording of ``--side`` x ``--side`` LR pixels with
``41 * --frames`` spike frames (one output frame per 41: the network's window and the default
``--every``), reconstructed at x4 through ``pipeline.jobs.reconstruct.reconstruct(..., client=...)`` on
a local cluster of one GPU worker (a Dask worker advertising ``GPU=1``, so that the job takes the
GPU-worker path: ``pipeline.compute.cluster.dask_client(workers=1, gpus=1)`` where it exists, else one
worker with one thread and ``GPU=1``, as compose's ``gpu-worker``).

**``--stand-in S``: the CPU proxy, measured without a GPU.** The network is replaced, in the
worker, by :class:`StandInDevice` (a measuring instrument: it lives in ``_gpu_standin.py`` and is never a
product path) with the same input and output shapes: a batch of n windows sleeps n * S seconds, leaving
the CPU free as a GPU kernel does, and returns a fixed, natural-looking uint8 HR image made once
from the recording (its first window's TFP image at the store's gain, enlarged to HR), so that
compressing it costs what real output costs. Everything else is the real GPU-worker path: reads,
the packed transfer, tiling, the overlap of tasks, compression, Zarr writes, commits, Dask. On the
device-side path (``NetworkReconstructor.device_images``) the stand-in replaces ``device_images``
(unpacking, network and exposure all run on the device); on the old path (before #35, which had
none) it replaces the model, and unpacking and exposure run on the CPU as that path ran them (so
does its averaging of views over the float HR rates, ``sum(...) / 1``, which a GPU would run:
``--profile`` measures it alone). It reports, per repeat and as medians:

- ``job_seconds_per_frame``: the wall time of a warm job (cluster started, the job run once untimed
  before) per output frame; goal <= 1.15 S (the device never waits);
- ``non_network_cpu_seconds_per_frame``: CPU time (user + system) of the worker process during the
  timed job per output frame (the stand-in uses none); goal <= 0.15 s. The system share is given
  apart: on a VM it includes the host's cost of guest pages touched for the first time (the page
  cache that each job's ~43 MB per frame of output fills), which varies from run to run;
- the device's busy share (the stand-in's sleeps over the job's wall time), and with ``--profile``
  what each step of a task costs in CPU per frame, measured in this process on one task's data
  (read and decompress, the reconstructor's host work around the stand-in, compress and write).

**Without ``--stand-in``: the real network** (``--device cuda`` on a lent GPU; ``--device cpu``
for a smoke run, ``--quick``), for each of ``--configs`` (lite, full) x ``--precisions`` (fp32,
bf16): ``pipeline_frames_per_second`` (the warm job as above, the pipeline choosing the tile
unless ``--tile`` is given), ``reconstructor_frames_per_second`` (``method.many`` on the same
windows in this process) and ``forward_frames_per_second`` (the model alone on the pipeline's
windows, unpacked and on the device, synchronised before and after each pass, as many windows a pass
as the job's GPU tasks take, fewer if they do not fit beside this process's own), the forward pass
in FLOP/s (counted by ``torch.utils.flop_counter``) and as a share of the GPU's dense bf16 peak,
and GPU-hours per terabyte of capture (8 M spike frames, one output per 41: 195,122 output frames)
at ``pipeline_frames_per_second``. ``--cli`` adds the whole command line as a user runs it, cold.

The recording is made by the project's simulator (``pipeline.jobs.simulate``, a still picture, about 20 s
for 984 frames of 1000x1000 on 2 cores) and cached in ``/tmp/cscsr_bench`` by its parameters.

Run: ``python benchmarks/gpu_pipeline.py --stand-in 0.25 --frames 24 --side 1000 --tile 1000
[--repeats 3] [--profile] [--out DIR]``, or ``python benchmarks/gpu_pipeline.py --device cuda
--frames 40 --configs lite,full --precisions fp32,bf16 [--fast-gpu] [--merge] [--out DIR]``.
Results: ``DIR/gpu_pipeline.json`` (default ``benchmarks/results``); ``--merge`` keeps the runs of
other configurations already in that file (one lease command per configuration).

This file is the command line; its pieces live beside it, named with ``_`` as ``_common.py`` (helpers, not
benchmarks: ``run_all.py`` skips them): ``_gpu_recording.py`` (the recording and its geometry),
``_gpu_standin.py`` (the stand-in network), ``_gpu_job.py`` (the cluster and the timed job),
``_gpu_proxy_mode.py`` (``--stand-in``), ``_gpu_network_mode.py`` (the real network) and ``_gpu_report.py``
(the tables and the JSON).
"""

import argparse
import os
import shutil
import tempfile
from pathlib import Path

from _common import RESULTS, load_average
from _gpu_network_mode import measure_network, run_cli
from _gpu_proxy_mode import measure_stand_in
from _gpu_recording import CACHE, OUTPUT_FRAMES_PER_TB, SCALE, WINDOW, cached_recording
from _gpu_report import print_network, print_stand_in, save


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stand-in", type=float, default=None, metavar="S",
                        help="the CPU proxy: a stand-in network of S seconds per window (no GPU needed)")
    parser.add_argument("--frames", type=int, default=40, help="output frames (41 spike frames each; default 40)")
    parser.add_argument("--side", type=int, default=1000, help="LR height = width, even (default 1000)")
    parser.add_argument("--tile", type=int, default=None, help="LR tile (default: the pipeline's choice)")
    parser.add_argument("--gpu-batch", type=int, default=None, help="windows per pass on the GPU worker (default: "
                        "the pipeline's choice)")
    parser.add_argument("--configs", default="lite", help="network configurations, comma-separated (lite,full)")
    parser.add_argument("--precisions", default="fp32", help="fp32,bf16")
    parser.add_argument("--weights", default=None, help="a weights file instead of the shipped ones (one config)")
    parser.add_argument("--fast-gpu", action="store_true", help="ReconstructOptions(fast_gpu=True): channels-last, "
                        "cuDNN autotuning, torch.compile on the GPU worker")
    parser.add_argument("--forward-batch", type=int, default=None, help="windows per pass of the forward pass alone "
                        "(default: the reconstructor's batch)")
    parser.add_argument("--device", choices=["cuda", "cpu"], default=None,
                        help="the real network's device (default: cuda if torch sees a GPU, else cpu)")
    parser.add_argument("--repeats", type=int, default=None, help="timed runs (default 3 with --stand-in, else 2)")
    parser.add_argument("--profile", action="store_true", help="with --stand-in: CPU per frame of each task step")
    parser.add_argument("--cli", action="store_true", help="also time the command line, cold (real network)")
    parser.add_argument("--merge", action="store_true", help="keep other configurations' runs already in the JSON")
    parser.add_argument("--out", type=Path, default=RESULTS, help=f"folder for the JSON (default {RESULTS})")
    parser.add_argument("--quick", action="store_true", help="a smoke run: side 64, 2 frames, 1 repeat")
    args = parser.parse_args()
    if args.quick:
        args.side, args.frames, args.repeats = 64, 2, 1
    args.repeats = args.repeats or (3 if args.stand_in is not None else 2)
    configs, precisions = args.configs.split(","), args.precisions.split(",")
    if args.side < 8 or args.side % 2 or args.frames < 1 or args.repeats < 1:
        parser.error("--side must be an even number >= 8, --frames and --repeats >= 1")
    if args.stand_in is not None and args.stand_in < 0:
        parser.error("--stand-in must be >= 0 seconds")
    if args.weights and len(configs) > 1:
        parser.error("--weights names one network: give one --configs")

    import torch

    if args.stand_in is not None:
        device = "cpu"
    else:
        device = args.device or ("cuda" if torch.cuda.is_available() else "cpu")
        if device == "cuda" and not torch.cuda.is_available():
            parser.error("--device cuda: torch sees no GPU")
    if device == "cpu":
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # the workers (spawned from here) pick their device alone
    gpu = torch.cuda.get_device_name() if device == "cuda" else None

    load_start = load_average()
    spike_frames = WINDOW * args.frames
    store, simulate_seconds = cached_recording(args.side, spike_frames)
    work = Path(tempfile.mkdtemp(prefix="gpu-pipeline-", dir=CACHE))
    common = {"side": args.side, "scale": SCALE, "window": WINDOW, "every": WINDOW, "output_frames": args.frames,
              "spike_frames": spike_frames, "repeats": args.repeats, "recording": store,
              "simulate_seconds_now": simulate_seconds, "torch": torch.__version__, "device": device, "gpu": gpu,
              "load_average_at_start": load_start}
    try:
        if args.stand_in is not None:
            result = {**common, **measure_stand_in(args, store, work)}
            print_stand_in(result, args)
        else:
            runs = [measure_network(args, store, work, config, precision, device, gpu)
                    for config in configs for precision in precisions]
            result = {**common, "mode": "network", "output_frames_per_terabyte": OUTPUT_FRAMES_PER_TB, "runs": runs}
            if args.cli:
                result["cli_seconds"] = run_cli(store, work / "cli.zarr", runs[0]["weights"], device)
            print_network(result, args)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"\nLoad average at start {load_start}, at end {load_average()}.")
    print(f"(results: {save(args.out, result, args.merge)})")


if __name__ == "__main__":
    main()
