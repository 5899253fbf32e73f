"""Test-set quality of the network's CPU variants: ``--backend onnx`` and ``--precision bf16`` against
PyTorch in fp32 (the reference), through the whole Dask job.

What: the held-out test set (``cscsr make-testset``: astronaut, coffee, chelsea at three alphas, 3
truth frames each, 27 images) reconstructed by ``--method cscsr`` once per variant, as
``cscsr evaluate-testset`` does for the method; PSNR/SSIM by scikit-image on the 8-bit output
against the truth, and the largest 8-bit difference from the reference's frames.
Goal (#25): every variant within 0.05 dB of fp32 PyTorch's mean PSNR.

    python benchmarks/backend_quality.py [--weights lite] [--variants torch,onnx,bf16] [--workers 2]
"""

import argparse
import dataclasses
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import load_average, markdown_table, save_results

VARIANTS = {"torch": {"backend": "torch", "precision": "fp32"},  # the reference
            "onnx": {"backend": "onnx", "precision": "fp32"},
            "bf16": {"backend": "torch", "precision": "bf16"}}
GOAL_DB = 0.05


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", default="lite", help="weights file, or lite or full (default lite)")
    parser.add_argument("--variants", default="torch,onnx,bf16", help=f"comma-separated, from {', '.join(VARIANTS)}")
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    variants = args.variants.split(",")
    if variants[0] != "torch" or not set(variants) <= set(VARIANTS):
        parser.error(f"--variants: torch first (the reference), then any of {', '.join(VARIANTS)}")

    from pipeline.compute.cluster import dask_client
    from pipeline.jobs.evaluate import checked_evaluation
    from pipeline.stores.ground_truth import read_truth
    from pipeline.jobs.reconstruct import reconstruct
    from pipeline.stores.spike_store import open_spike_store
    from pipeline.jobs.testset import items, make_testset
    from pipeline.stores.video_store import VIDEO, open_video_store
    from stages.measures.metrics import psnr, ssim

    load_start = load_average()
    work = Path(tempfile.mkdtemp(prefix="backend-quality-"))
    scores = {v: [] for v in variants}  # (psnr, ssim) per image
    worst = {v: 0 for v in variants}  # largest 8-bit difference from the reference
    seconds = {v: 0.0 for v in variants}
    try:
        testset = str(work / "testset")
        make_testset(testset, workers=args.workers, progress=False)
        with dask_client(workers=args.workers) as client:
            for item in items():
                store = f"{testset}/{item.name}.zarr"
                _, _, options = checked_evaluation(store, ["cscsr"], args.weights)
                truth = read_truth(open_spike_store(store))[0][:]
                reference = None
                for variant in variants:
                    out = str(work / f"{item.name}-{variant}.zarr")
                    start = time.perf_counter()
                    reconstruct(store, out, dataclasses.replace(options["cscsr"], **VARIANTS[variant]), client=client,
                                progress=False)
                    seconds[variant] += time.perf_counter() - start
                    video = open_video_store(out)[VIDEO][: len(truth)]
                    scores[variant] += [(psnr(frame, true), ssim(frame, true)) for frame, true in zip(video, truth)]
                    reference = video if reference is None else reference
                    worst[variant] = max(worst[variant], int(np.abs(video.astype(int) - reference.astype(int)).max()))
                print(f"{item.name}: done", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    mean = {v: (float(np.mean([p for p, _ in scores[v]])), float(np.mean([s for _, s in scores[v]]))) for v in variants}
    base = mean["torch"][0]
    rows = [[v, f"{mean[v][0]:.3f}", f"{mean[v][1]:.4f}", f"{mean[v][0] - base:+.3f}", worst[v],
             f"{seconds[v] / len(scores[v]):.2f}",
             "reference" if v == "torch" else ("PASS" if abs(mean[v][0] - base) <= GOAL_DB else "FAIL")]
            for v in variants]
    print(f"## `{args.weights}` on the test set ({len(scores['torch'])} images), per CPU variant\n")
    print(markdown_table(["variant", "mean PSNR (dB)", "mean SSIM", "vs fp32 PyTorch (dB)",
                          "largest 8-bit difference", "s per image (job)", f"within {GOAL_DB} dB"], rows))
    print(f"\nLoad average at start {load_start}, at end {load_average()}.")
    path = save_results("backend_quality", {"weights": args.weights, "workers": args.workers, "goal_db": GOAL_DB,
                                            "mean": mean, "largest_difference": worst, "seconds": seconds,
                                            "load_average_at_start": load_start})
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
