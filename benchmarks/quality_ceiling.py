"""Ceilings of the test-set quality table: what perfect intensities would give.

What: on the held-out test set (``cscsr make-testset``: astronaut, coffee, chelsea, x4,
alpha 0.6 / 0.8 / 1.0, three truth frames each), PSNR and SSIM of four references made from
the ground truth instead of spikes (``stages.measures.references``): the exact LR picture enlarged
bicubically; the exact LR mosaic demosaicked (VNG) and enlarged, which is TFP / TFI with no
spike noise and no motion blur; that mosaic as a still scene's long-run firing rate reads it
through the test set's noiseless zero-reset sensor, whose firing period quantises intensity
(TFP's reading: the ceiling of TFP and TFI); and each period read as the mean intensity of
the pixels that have it in these very pictures (an oracle fitted per alpha: the bound on any
estimator of a still pixel from its own spikes). A method above the last uses context
(neighbours, motion) that per-pixel estimators do not.

Optionally (``--summary OUT/summary.csv`` of ``cscsr evaluate-testset``) the methods' rows
are printed beside the ceilings. Deterministic: one evaluation, no timing.

Run: ``python benchmarks/quality_ceiling.py [--testset DIR] [--summary CSV]`` (without
``--testset`` it makes the test set under ``benchmarks/results/testset`` first, ~2 min).
"""

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from _common import RESULTS, markdown_table, save_results
from pipeline.stores.spike_store import open_spike_store
from pipeline.jobs.testset import average_per_alpha, make_testset
from stages.measures.metrics import psnr, ssim
from stages.measures.references import (exact_lr_bicubic, exact_mosaic_demosaicked, mean_level_per_period, read_periods,
                               steady_state_mosaic)

def references(truth: np.ndarray, cfa: str, scale: int, alpha: float, levels: dict[int, float]) -> dict:
    """Name -> the reference picture made from one (s*H, s*W, 3) uint8 truth frame."""
    return {
        "exact LR picture, bicubic": exact_lr_bicubic(truth, scale),
        "exact LR mosaic, VNG, bicubic": exact_mosaic_demosaicked(truth, cfa, scale),
        "still scene, long-run rate as TFP reads it": steady_state_mosaic(truth, cfa, scale, alpha, "zero"),
        "still scene, best reading of each period (oracle)": read_periods(truth, cfa, scale, alpha, levels),
    }


def ceilings(testset: Path) -> list[dict]:
    """One row per reference and alpha (and 'all'): mean PSNR / SSIM over the truth frames."""
    manifest = json.loads((testset / "manifest.json").read_text())
    if manifest["reset"] != "zero":
        raise SystemExit(f"{testset}: the period ceilings assume the zero reset, not {manifest['reset']!r}")
    cfa, scale = manifest["cfa"], manifest["scale"]
    truths = {item["store"]: open_spike_store(str(testset / item["store"])).group["truth"][:]
              for item in manifest["items"]}
    levels = {alpha: mean_level_per_period([t for item in manifest["items"] if item["alpha"] == alpha
                                            for t in truths[item["store"]]], cfa, scale, alpha)
              for alpha in {item["alpha"] for item in manifest["items"]}}  # fitted per alpha over every picture
    scores = [{"method": name, "alpha": item["alpha"], "psnr": psnr(estimate, frame), "ssim": ssim(estimate, frame)}
              for item in manifest["items"] for frame in truths[item["store"]]
              for name, estimate in references(frame, cfa, scale, item["alpha"], levels[item["alpha"]]).items()]
    return average_per_alpha(scores, ("psnr", "ssim"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--testset", type=Path, help="a test set made by cscsr make-testset (default: make one)")
    parser.add_argument("--summary", type=Path, help="summary.csv of cscsr evaluate-testset, printed beside")
    args = parser.parse_args()
    testset = args.testset or RESULTS / "testset"
    if not (testset / "manifest.json").exists():
        make_testset(str(testset), overwrite=True, progress=False)
    rows = ceilings(testset)
    if args.summary:
        with args.summary.open() as handle:
            rows = [{"method": r["method"], "alpha": r["alpha"], "psnr": float(r["psnr"]), "ssim": float(r["ssim"])}
                    for r in csv.DictReader(handle)] + rows
    alphas = [a for a in dict.fromkeys(str(r["alpha"]) for r in rows) if a != "all"]
    table = []
    for method in dict.fromkeys(r["method"] for r in rows):
        mine = {str(r["alpha"]): r for r in rows if r["method"] == method}
        table.append([method, *(f"{mine[a]['psnr']:.2f}" for a in alphas),
                      f"{mine['all']['psnr']:.2f}", f"{mine['all']['ssim']:.3f}"])
    print(markdown_table(["method", *(f"α {a}" for a in alphas), "mean PSNR", "mean SSIM"], table))
    save_results("quality_ceiling", {"testset": str(testset), "rows": rows})


if __name__ == "__main__":
    main()
