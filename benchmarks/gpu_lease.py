"""A GPU lease in a few commands: check, benchmark, train ``full`` in resumable slices, export.

A lease (docs/gpu.md) is about 30 minutes of one GPU, commands of at most 10 minutes, 64 MiB
of files sent along and 8 files of 16 MiB back. Each step below is one command and writes
what must come back into ``--out`` (``$OUT`` on the GPU machine):

    pack PICTURES... --sequences FRAMES --dest .gpu-data/pictures   (here, before the lease) natural training
        pictures and sequences of frames re-encoded to fit the lease's 64 MiB (JPEG q88, short side
        at most --short-side px)
    prove   the GPU path proved in one command of at most --budget s (issue #46: benchmarks/gpu_prove.py):
            the device path against the CPU's bytes, fp32 and bf16, eager and --fast-gpu; the Dask job
            on one GPU worker beside the forward pass; peak GPU memory; prove.json after every step
    check   torch, CUDA, the GPU, bf16; torch clip synthesis (clips/s) beside numpy; a smoke
            training run of ``full`` (30 steps)
    bench   the inference benchmark (network_forward.py --device cuda): lite and full, fp32 and
            bf16, 180x320, a 256x256 tile and 1000x1000 LR at x4, with peak GPU memory
    train   ``full`` into --run (kept on the machine between calls), resuming if a checkpoint
            is there (or a portable checkpoint's parts, carried to a fresh machine), else from
            --init; stops cleanly inside --minutes; exports fp16 weights, the training log and
            a portable checkpoint (parts of at most 16 MiB: fp16 weights, bf16 Adam moments)
            into --out

Every step also runs on the CPU with tiny settings (``--tiny``, in fp32: bf16 on a CPU without native
bfloat16 is emulated, slowly): tests/test_gpu_lease.py does.

Run: ``python benchmarks/gpu_lease.py {pack,prove,check,bench,train} [options]``.
"""

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from _common import ROOT

RUN = ROOT / "training" / "full-gpu"  # ignored by git, so it stays on a warm machine between calls
# One recipe for every slice of the run: a resumed slice must not change what shapes the weights.
RECIPE = {"config": "full", "batch": 32, "lr_side": 48, "learning_rate": 3e-4, "warmup": 100, "decay_every": 2000,
          "checkpoint_every": 250, "validate_every": 500, "steps": 200_000}
TINY = {"config": "lite", "batch": 2, "lr_side": 16, "checkpoint_every": 2, "validate_every": 2, "steps": 4,
        "validation_clips": 2}


def pack(sources: list[str], dest: Path, sequences: list[str] = (), short_side: int = 360, quality: int = 88) -> dict:
    """Re-encode every picture under ``sources`` and ``sequences`` (folders of sub-folders of consecutive frames,
    kept whole: their frames' numbers stay consecutive, so training uses their motion) into ``dest``, one
    sub-folder per source folder."""
    import cv2

    from cscsr.training.training_data import picture_files

    dest.mkdir(parents=True, exist_ok=True)
    count, size = 0, 0
    for source in [*sources, *sequences]:
        for name in picture_files([source]):
            image = cv2.imread(name, cv2.IMREAD_COLOR)
            factor = short_side / min(image.shape[:2])
            if factor < 1:
                image = cv2.resize(image, None, fx=factor, fy=factor, interpolation=cv2.INTER_AREA)
            relative = Path(name).relative_to(source).with_suffix(".jpg")
            target = dest / Path(source).name / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(target), image, [cv2.IMWRITE_JPEG_QUALITY, quality])
            count, size = count + 1, size + target.stat().st_size
    return {"pictures": count, "mib": size / 2**20}


def check(out: Path, tiny: bool) -> None:
    import numpy as np
    import torch

    from cscsr.training.synthesis import prepare, synthesise
    from cscsr.training.training_data import random_plan, run_plan

    cuda = torch.cuda.is_available() and not tiny
    device = "cuda" if cuda else "cpu"
    report = {"torch": torch.__version__, "python": sys.version.split()[0], "device": device}
    if cuda:
        props = torch.cuda.get_device_properties(0)
        report |= {"gpu": props.name, "gpu_memory_gib": props.total_memory / 2**30,
                   "bf16": torch.cuda.is_bf16_supported(), "cuda": torch.version.cuda}
    print(json.dumps(report), flush=True)

    batch, side = (2, 16) if tiny else (24, 48)
    plans = [random_plan([0, 995, i], lr_side=side, scale=4) for i in range(batch)]
    start = time.perf_counter()
    prepared = prepare(plans)
    prepare_s = time.perf_counter() - start
    synthesise(prepared, device)
    times = []
    for _ in range(1 if tiny else 5):
        start = time.perf_counter()
        synthesise(prepared, device)
        if cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    start = time.perf_counter()
    for plan in plans[: 2 if tiny else 6]:
        run_plan(plan)
    numpy_clip_s = (time.perf_counter() - start) / (2 if tiny else 6)
    synthesis = {"batch": batch, "lr_side": side, "device_clips_per_s": batch / float(np.median(times)),
                 "cpu_prepare_clips_per_s": batch / prepare_s, "numpy_clips_per_s_one_core": 1 / numpy_clip_s}
    print(json.dumps({"synthesis": synthesis}), flush=True)

    smoke = Path("/tmp/cscsr-smoke")
    shutil.rmtree(smoke, ignore_errors=True)
    options = (TINY if tiny else {**RECIPE, "steps": 30, "checkpoint_every": 30, "validate_every": 30}) | {
        "device": device, "precision": "fp32" if tiny else "bf16"}  # bf16 on a CPU may be emulated: slow
    started = time.perf_counter()
    train_slice(options, smoke, resume=False)
    log = [json.loads(line) for line in (smoke / "log.jsonl").read_text().splitlines()]
    report |= {"synthesis": synthesis, "smoke": {"steps": log[-1]["step"], "seconds": time.perf_counter() - started,
                                                 "samples_per_s": log[-1]["samples_per_s"]}}
    (out / "check.json").write_text(json.dumps(report, indent=1))
    print(json.dumps({"smoke": report["smoke"]}), flush=True)


def train_slice(options: dict, run: Path, *, resume: bool, log=print) -> Path:
    from cscsr.training.train import TrainOptions, train

    return train(TrainOptions(**options), run, resume=resume, log=lambda line: log(line, flush=True),
                 command="benchmarks/gpu_lease.py train " + json.dumps(options, sort_keys=True))


def train_command(out: Path, run: Path, minutes: float, pictures: list[str], init: str, decay_every: int,
                  tiny: bool, portable_weights: str = "float16", steps: int = 0) -> None:
    import torch

    from cscsr.weights.portable_checkpoint import portable_parts
    from cscsr.training.train import export_portable, export_weights

    device = "cuda" if torch.cuda.is_available() and not tiny else "cpu"
    resume = (run / "checkpoint.safetensors").exists() or bool(portable_parts(run, complete=False))
    options = {**(TINY if tiny else RECIPE), "device": device, "precision": "fp32" if tiny else "bf16",
               "time_budget": minutes * 60,
               "pictures": os.pathsep.join(pictures)}
    if decay_every:
        options["decay_every"] = decay_every
    if init and not resume:
        options["init"] = init
    if tiny and resume:
        options["steps"] = TINY["steps"] * 2
    if steps:
        options["steps"] = steps
    print(f"{'resuming' if resume else 'starting'} {run} on {device} for at most {minutes} min", flush=True)
    train_slice(options, run, resume=resume)
    # each slice replaces the previous slice's exports in OUT (its own)
    step = export_weights(run, out / f"cscsr-{options['config']}.safetensors", storage="float16",
                          command="benchmarks/gpu_lease.py train (fp16 export)", overwrite=True)
    shutil.copy(run / "log.jsonl", out / "log.jsonl")
    _, parts = export_portable(run, out, weights=portable_weights, overwrite=True)
    print(f"exported step {step} to {out}: weights, log and a portable checkpoint in {len(parts)} parts "
          f"({sum(p.stat().st_size for p in parts) / 2**20:.1f} MiB)", flush=True)


def main() -> None:
    if sys.argv[1:2] == ["prove"]:  # its own options: benchmarks/gpu_prove.py
        import gpu_prove

        gpu_prove.main(sys.argv[1:])
        return
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("step", choices=["pack", "check", "bench", "train"])
    parser.add_argument("sources", nargs="*", help="pack: folders of pictures")
    parser.add_argument("--sequences", action="append", default=[], help="pack: a folder of frame sequences")
    parser.add_argument("--dest", default=str(ROOT / ".gpu-data" / "pictures"), help="pack: where to write")
    parser.add_argument("--short-side", type=int, default=360, help="pack: largest short side, px")
    parser.add_argument("--out", default=os.environ.get("OUT", str(ROOT / "benchmarks" / "results" / "gpu")))
    parser.add_argument("--run", default=str(RUN), help="train: the training folder")
    parser.add_argument("--minutes", type=float, default=8.5, help="train: time budget of this slice")
    parser.add_argument("--pictures", action="append", default=[], help="train: a folder of training pictures")
    parser.add_argument("--init", default="", help="train: weights to start a new run from")
    parser.add_argument("--decay-every", type=int, default=0, help="train: change the decay (annealing)")
    parser.add_argument("--steps", type=int, default=0, help="train: steps in all (default: the recipe's)")
    parser.add_argument("--portable-weights", default="float16", choices=["float16", "float32"],
                        help="train: storage of the weights in the portable checkpoint")
    parser.add_argument("--tiny", action="store_true", help="CPU dry run with tiny settings")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    if args.step == "pack":
        print(json.dumps(pack(args.sources, Path(args.dest), args.sequences, args.short_side)))
    elif args.step == "check":
        check(out, args.tiny)
    elif args.step == "bench":
        subprocess.run([sys.executable, str(ROOT / "benchmarks" / "network_forward.py"), "--device", "cuda",
                        "--repeats", "5", "--out", str(out)], check=True)
    else:
        train_command(out, Path(args.run), args.minutes, args.pictures, args.init, args.decay_every, args.tiny,
                      args.portable_weights, args.steps)


if __name__ == "__main__":
    main()
