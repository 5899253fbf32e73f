"""Held-out quality of mono weights (docs/training.md, `lite-mono`), or with ``--cfa rggb`` of colour ones: 16 stores no
training saw, scored by ``cscsr evaluate`` beside TFP and TFI, each weights file given in the same run.

The stores: 256x256 centre crops of 8 pictures from test sets left out of training (BSD100 101085, 160068, 241048,
41033; Set14 pepper and zebra; Urban100 img_005, img_051), each simulated twice, with subtract and with zero reset:
``--cfa CFA --scale 4 --frames 123 --motion random --truth-every 41 --seed 100+i``, brightness (alpha) alternating
0.6 and 0.8 (with subtract reset 0.6 for even i; with zero reset 0.8), no noise: LR 64x64, x4, 3 truth frames each.

    python benchmarks/mono_quality.py [--cfa mono|rggb|...] [--pictures TRAINING_DATA] [--weights FILE ...]
        [--work DIR] [--json]

``--pictures``: the training-data folder holding those test sets (README, Training; not distributed; default
``../shared/training-data`` beside the repository: skipped where it is not). ``--weights`` (repeatable): default
the shipped ``lite-mono`` (``lite`` for a colour ``--cfa``). Prints the table of mean PSNR per reset, over all 16,
and mean SSIM; ``--json`` the same as JSON, with each store's PSNR.
"""

import argparse
import json
import statistics
from pathlib import Path

from _common import ROOT, markdown_table

PICTURES = ("bsds500_val_bsd100/101085.jpg", "bsds500_val_bsd100/160068.jpg", "bsds500_val_bsd100/241048.jpg",
            "bsds500_val_bsd100/41033.jpg", "set5_set14/set14_pepper.png", "set5_set14/set14_zebra.png",
            "urban100/img_005_SRF_2_HR.png", "urban100/img_051_SRF_2_HR.png")
RESETS = ("subtract", "zero")
CROP = 256  # HR pixels: LR 64x64 at x4
ALPHAS = (0.6, 0.8)  # the brightness of picture i, alternating: subtract reset 0.6 for even i, zero reset 0.8


def centre_crop(src: Path, dest: Path) -> None:
    import imageio.v3 as iio

    image = iio.imread(src)
    image = image[..., :3] if image.ndim == 3 else image
    y, x = (image.shape[0] - CROP) // 2, (image.shape[1] - CROP) // 2
    iio.imwrite(dest, image[y : y + CROP, x : x + CROP])


def stores(pictures: Path, work: Path, cfa: str = "mono") -> list[tuple[str, str, Path]]:
    """(picture, reset, store) of the 16 stores, simulated once into ``work`` (kept: a later run reuses them)."""
    from pipeline.jobs.simulate import SimulateOptions, simulate

    made = []
    for i, name in enumerate(PICTURES):
        crop = work / f"{i}.png"
        if not crop.exists():
            centre_crop(pictures / name, crop)
        for reset in RESETS:
            store = work / (f"{i}-{reset}.zarr" if cfa == "mono" else f"{i}-{reset}-{cfa}.zarr")
            if not store.exists():
                options = SimulateOptions(scale=4, cfa=cfa, frames=123, motion="random", truth_every=41,
                                          seed=100 + i, reset=reset, brightness=ALPHAS[(i + RESETS.index(reset)) % 2])
                simulate(str(crop), str(store), options, workers=1, progress=False)
            made.append((name, reset, store))
    return made


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pictures", type=Path, default=ROOT.parent / "shared" / "training-data",
                        help="the training-data folder (its test sets)")
    parser.add_argument("--cfa", default="mono", help="the stores' colour pattern (default mono)")
    parser.add_argument("--weights", action="append", help="a weights file (repeat; default lite-mono, or lite)")
    parser.add_argument("--work", default="/tmp/cscsr-mono-quality", help="where the stores and scores go")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if not all((args.pictures / name).exists() for name in PICTURES):
        print(f"skipped: the test pictures are not under {args.pictures} (--pictures)")
        return
    shipped = "cscsr-lite-mono.safetensors" if args.cfa == "mono" else "cscsr-lite.safetensors"
    args.weights = args.weights or [str(ROOT / "cscsr" / "weights" / shipped)]
    from distributed import Client, LocalCluster

    from pipeline.jobs.evaluate import evaluate

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    scores: dict[str, dict[str, list]] = {}  # row -> reset -> [(psnr, ssim)]
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0") as cluster, Client(cluster) as client:
        for name, reset, store in stores(args.pictures, work, args.cfa):
            for k, weights in enumerate(args.weights):
                methods = ["tfp", "tfi", "cscsr"] if k == 0 else ["cscsr"]
                rows = evaluate(str(store), methods, str(work / f"eval-{store.stem}-{k}"), weights=weights,
                                client=client, progress=False, overwrite=True)
                for row in rows:
                    label = weights if row["method"] == "cscsr" else row["method"]
                    scores.setdefault(label, {}).setdefault(reset, []).append((row["psnr"], row["ssim"]))
    table = {}
    for label, by_reset in scores.items():
        every = [s for reset in RESETS for s in by_reset[reset]]
        table[label] = {**{f"{reset}_psnr": statistics.mean(p for p, _ in by_reset[reset]) for reset in RESETS},
                        "psnr": statistics.mean(p for p, _ in every), "ssim": statistics.mean(s for _, s in every),
                        "stores": len(every), "psnr_each": [p for p, _ in every]}
    if args.json:
        print(json.dumps(table, indent=1))
        return
    print(markdown_table(["method", "subtract reset", "zero reset", "all 16 stores", "SSIM (all)"],
                         [[label, f"{t['subtract_psnr']:.2f} dB", f"{t['zero_psnr']:.2f} dB", f"{t['psnr']:.2f} dB",
                           f"{t['ssim']:.3f}"] for label, t in table.items()]))


if __name__ == "__main__":
    main()
