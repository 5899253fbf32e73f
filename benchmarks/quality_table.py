"""The test-set quality table: PSNR / SSIM per alpha, median time per image, the gap to the goal.

What: ``pipeline.jobs.testset.evaluate_testset`` (what ``cscsr evaluate-testset`` runs) on the
held-out test set (``cscsr make-testset``: astronaut, coffee, chelsea, x4, alpha 0.6 / 0.8 /
1.0, three truth frames each) for the classic methods and the network with the weights it
ships (or ``--weights``), ``--repeats`` times on one Dask worker. PSNR and SSIM are
deterministic: the script fails if any repeat differs from the first. Time per image is the
median over the repeats of each method's whole Dask job divided by its images, and is given
as a ratio to TFI's in the same run. Beside each network row: its parameters and the training
budget its weights record (steps, command). The figure the goal is about: the network's mean
PSNR minus the best classic method's (goal >= 2 dB, printed as PASS/FAIL, never asserted).

Run: ``python benchmarks/quality_table.py [--testset DIR] [--repeats 3] [--methods ...]
[--weights FILE]`` (without ``--testset`` it makes the test set under
``benchmarks/results/testset`` first, ~2 min; then about 2 minutes a repeat).
"""

import argparse
import tempfile
from pathlib import Path

from _common import RESULTS, load_average, markdown_table, median, save_results
from cscsr.weights.model_info import model_info
from cscsr.weights.weights_io import default_weights, read_metadata
from pipeline.jobs.testset import evaluate_testset, make_testset

CLASSIC = ("tfp", "tfi")
GOAL_DB = 2.0


def _scores(rows: list[dict]) -> list[tuple]:
    return [(r["method"], r["alpha"], r["psnr"], r["ssim"]) for r in rows]


def repeated(testset: Path, methods: list[str], weights: str, repeats: int) -> tuple[list[dict], dict]:
    """(the rows of the first repeat, method -> seconds per image of every repeat); quality must not vary."""
    first, seconds = None, {}
    for repeat in range(repeats):
        with tempfile.TemporaryDirectory() as scratch:  # a new folder in it: an existing --out is refused
            rows = evaluate_testset(str(testset), methods, f"{scratch}/evaluation", weights=weights, workers=1,
                                    progress=False)
        if first is not None and _scores(rows) != _scores(first):
            raise SystemExit(f"repeat {repeat + 1} scored differently from the first: the evaluation is not deterministic")
        first = first or rows
        for r in rows:
            if r["alpha"] == "all":
                seconds.setdefault(r["method"], []).append(r["seconds_per_image"])
        print(f"repeat {repeat + 1}/{repeats}: " + ", ".join(f"{m} {s[-1]:.2f} s/image" for m, s in seconds.items()),
              flush=True)
    return first, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--testset", type=Path, help="a test set made by cscsr make-testset (default: make one)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--methods", default="tfp,tfi,cscsr,cscsr-ensemble")
    parser.add_argument("--weights", help="network weights (default: the shipped lite weights)")
    args = parser.parse_args()
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    weights = args.weights or str(default_weights("lite"))
    testset = args.testset or RESULTS / "testset"
    if not (testset / "manifest.json").exists():
        make_testset(str(testset), overwrite=True, progress=False)

    rows, seconds = repeated(testset, methods, weights, args.repeats)
    alphas = [a for a in dict.fromkeys(r["alpha"] for r in rows) if a != "all"]
    overall = {r["method"]: r for r in rows if r["alpha"] == "all"}
    times = {m: median(s) for m, s in seconds.items()}
    about = read_metadata(weights)
    parameters = model_info(weights=weights)["parameters (network, as the paper counts)"]
    budget = f"{about.get('steps', '?')} steps; {about.get('command', '?')}"
    table = []
    for method in overall:
        per_alpha = {r["alpha"]: r["psnr"] for r in rows if r["method"] == method}
        network = method not in CLASSIC
        table.append([method, *(f"{per_alpha[a]:.2f}" for a in alphas), f"{overall[method]['psnr']:.2f}",
                      f"{overall[method]['ssim']:.3f}", f"{times[method]:.2f}",
                      f"{times[method] / times['tfi']:.1f}" if "tfi" in times else "—",
                      parameters if network else "—", about.get("steps", "?") if network else "—"])
    print(f"\nload average: {load_average()}")
    print(markdown_table(["method", *(f"α {a}" for a in alphas), "mean PSNR", "mean SSIM",
                         f"s / image (median of {args.repeats})", "× TFI time", "parameters", "training steps"], table))
    print(f"\nweights: {weights}\ntraining budget: {budget}")
    classic = [m for m in overall if m in CLASSIC]
    gaps = {}
    if classic:
        best = max(classic, key=lambda m: overall[m]["psnr"])
        for method in (m for m in overall if m not in CLASSIC):
            gaps[method] = overall[method]["psnr"] - overall[best]["psnr"]
            verdict = "PASS" if gaps[method] >= GOAL_DB else f"FAIL ({GOAL_DB - gaps[method]:.2f} dB short)"
            print(f"{method} over the best classic ({best}): {gaps[method]:+.2f} dB mean PSNR; goal >= {GOAL_DB} dB: "
                  f"{verdict}")
    save_results("quality_table", {"testset": str(testset), "weights": weights, "training_budget": budget,
                                   "repeats": args.repeats, "rows": rows, "seconds_per_image": seconds,
                                   "median_seconds_per_image": times, "gain_over_best_classic_db": gaps})


if __name__ == "__main__":
    main()
