"""The held-out test set, made reproducibly, and the quality table on it.

``cscsr make-testset OUT`` simulates one spike store per test picture (scikit-image's
astronaut, coffee, chelsea: never used in training) and brightness α ∈ {0.6, 0.8, 1.0}:
256x256 HR (LR 64x64, x4), RGGB, zero reset (the paper's simulator), no noise, 123 frames
on a random camera path with its own seed, truth at frames 20, 61, 102. Every parameter is
fixed here, and simulation is bit-identical whatever the workers, so the command regenerates
the same bytes (tested). ``cscsr evaluate-testset OUT`` runs ``cscsr evaluate`` on every
store and averages per method and α: PSNR, SSIM, seconds per image.
"""

import csv
import json
from dataclasses import dataclass

import numpy as np

from cscsr.training.training_data import TEST_PICTURES as PICTURES
from pipeline.compute.cluster import check_in_memory, check_scheduler, check_workers, dask_client
from pipeline.jobs.evaluate import check_methods, checked_evaluation, evaluate
from pipeline.stores.images import write_image
from pipeline.jobs.simulate import SimulateOptions, simulate
from pipeline.stores.lease import claimed
from pipeline.stores.outputs import EVALUATION, TESTSET, mark_folder, new_output
from pipeline.stores.storage import check_apart, resolve
from stages.errors import InputError
from stages.measures.montage import labelled, side_by_side
from stages.numbers import check_flag
from stages.reconstruction.methods import WINDOW

ALPHAS = (0.6, 0.8, 1.0)
HR_SIDE, SCALE, FRAMES, TRUTH_EVERY, SPEED = 256, 4, 3 * WINDOW, WINDOW, 0.5  # a truth frame a window, 3 windows


@dataclass(frozen=True)
class Item:
    picture: str
    alpha: float
    seed: int

    @property
    def name(self) -> str:
        return f"{self.picture}_a{self.alpha:.1f}"


def items() -> list[Item]:
    return [Item(p, a, 1000 + 10 * i + j) for i, p in enumerate(PICTURES) for j, a in enumerate(ALPHAS)]


def test_picture(name: str) -> np.ndarray:
    """A bundled picture, centre-cropped square, resized to 256x256 (area), uint8 RGB."""
    import cv2
    from skimage import data

    image = getattr(data, name)()
    side = min(image.shape[:2])
    top, left = (image.shape[0] - side) // 2, (image.shape[1] - side) // 2
    return cv2.resize(image[top : top + side, left : left + side], (HR_SIDE, HR_SIDE), interpolation=cv2.INTER_AREA)


def make_testset(out: str, *, workers: int | None = None, overwrite: bool = False, progress: bool = True,
                 only: list[str] | None = None) -> list[str]:
    """Write the test set's sources and spike stores under ``out``; returns the store URLs.

    ``only``: item names (``astronaut_a0.6``, ...) to make, for tests; default all nine.
    """
    check_workers(workers)
    check_in_memory((out,))  # simulated into by worker processes
    chosen = [item for item in items() if only is None or item.name in only]
    if not chosen:
        raise InputError(f"no test-set items named {', '.join(only)}")
    fs, root = resolve(out)
    # replaces only a test set (the old one kept until the new one is made), removed if making it fails
    with claimed(out), new_output(out, overwrite=overwrite, kind=TESTSET, flag="--overwrite"):
        mark_folder(out, TESTSET)
        fs.makedirs(f"{root}/sources", exist_ok=True)
        stores = []
        for item in chosen:
            source = f"{out.rstrip('/')}/sources/{item.picture}.png"
            if not fs.exists(f"{root}/sources/{item.picture}.png"):
                write_image(source, test_picture(item.picture))
            store = f"{out.rstrip('/')}/{item.name}.zarr"
            simulate(source, store, SimulateOptions(scale=SCALE, cfa="rggb", brightness=item.alpha, frames=FRAMES,
                                                    motion="random", seed=item.seed, reset="zero", noise="none",
                                                    truth_every=TRUTH_EVERY, speed=SPEED), workers=workers,
                     progress=progress)
            stores.append(store)
        with fs.open(f"{root}/manifest.json", "w") as f:
            json.dump({"items": [item.__dict__ | {"store": f"{item.name}.zarr"} for item in chosen],
                       "hr_side": HR_SIDE, "scale": SCALE, "frames": FRAMES, "truth_every": TRUTH_EVERY, "speed": SPEED,
                       "cfa": "rggb", "reset": "zero", "noise": "none"}, f, indent=1)
    return stores


def evaluate_testset(testset: str, methods: list[str], out: str, *, weights: str | None = None,
                     workers: int | None = None, scheduler: str | None = None, progress: bool = True,
                     overwrite: bool = False) -> list[dict]:
    """Every method on every test store; rows averaged per (method, alpha), plus an 'all' row per method.

    ``out`` is a new output: an existing one is refused unless ``overwrite`` (and it is an evaluation)."""
    check_flag("--overwrite", overwrite)
    check_apart(out, testset, weights)
    check_methods(methods, weights)
    check_workers(workers, scheduler)
    check_in_memory((testset, out, weights))  # read and written by the reconstructions' worker processes
    fs, root = resolve(testset)
    if not fs.exists(f"{root}/manifest.json"):
        raise InputError(f"{testset} is not a test set (no manifest.json): make one with cscsr make-testset")
    with fs.open(f"{root}/manifest.json") as f:
        chosen = [Item(i["picture"], i["alpha"], i["seed"]) for i in json.load(f)["items"]]
    for item in chosen:  # every store and method checked before OUT is replaced
        checked_evaluation(f"{testset.rstrip('/')}/{item.name}.zarr", methods, weights)
    check_scheduler(scheduler)  # a named scheduler answers (within seconds) before OUT is claimed or replaced
    out_fs, out_root = resolve(out)
    # replaces only an earlier evaluation, with --overwrite (kept until this one is written), never a user's folder
    with claimed(out), new_output(out, overwrite=overwrite, kind=EVALUATION):
        mark_folder(out, EVALUATION)
        per_item = []
        with dask_client(workers=workers, scheduler=scheduler) as client:
            for item in chosen:
                rows = evaluate(f"{testset.rstrip('/')}/{item.name}.zarr", methods, f"{out.rstrip('/')}/{item.name}",
                                weights=weights, client=client, progress=progress)
                per_item += [row | {"picture": item.picture, "alpha": item.alpha} for row in rows]
        summary = average_per_alpha(per_item, ("psnr", "ssim", "seconds_per_image"))
        with out_fs.open(f"{out_root}/summary.csv", "w", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=list(summary[0]))
            writer.writeheader()
            writer.writerows(summary)
        write_image(f"{out.rstrip('/')}/crops.png", _crops(testset, out, methods, chosen))
    return summary


def average_per_alpha(rows: list[dict], keys: tuple[str, ...]) -> list[dict]:
    """Rows with ``method``, ``alpha`` and ``keys`` -> their means per (method, alpha), plus an 'all' row per method."""
    summary = []
    alphas = sorted({r["alpha"] for r in rows})
    for method in dict.fromkeys(r["method"] for r in rows):
        for alpha in (*alphas, "all"):
            chosen = [r for r in rows if r["method"] == method and (alpha == "all" or r["alpha"] == alpha)]
            summary.append({"method": method, "alpha": alpha} | {k: float(np.mean([r[k] for r in chosen])) for k in keys})
    return summary


def _crops(testset: str, out: str, methods: list[str], chosen: list[Item]) -> np.ndarray:
    """One 96x96 HR crop per test picture (its middle alpha, middle truth frame): truth, then every method."""
    from pipeline.stores.ground_truth import read_truth
    from pipeline.stores.spike_store import open_spike_store
    from pipeline.stores.video_store import VIDEO, open_video_store

    window = (1, slice(80, 176), slice(80, 176))
    rows = []
    for picture in dict.fromkeys(item.picture for item in chosen):
        alphas = [item for item in chosen if item.picture == picture]
        name = alphas[len(alphas) // 2].name
        truth, _ = read_truth(open_spike_store(f"{testset.rstrip('/')}/{name}.zarr"))
        tiles = [labelled(truth[window], "truth")]
        tiles += [labelled(open_video_store(f"{out.rstrip('/')}/{name}/{method}.zarr")[VIDEO][window], method)
                  for method in methods]
        rows.append(side_by_side(*tiles))
    return np.concatenate(rows, axis=0)
