"""``cscsr evaluate``: methods against a simulated store's ground truth, as numbers and pictures.

Each method runs through the same distributed reconstruction as ``cscsr reconstruct``, at
exactly the store's truth frames (window 41, one output every ``truth_every`` frames), into
``OUT/<method>.zarr``. PSNR and SSIM come from scikit-image. Writes ``OUT/metrics.csv``
(one row per method and frame), ``OUT/summary.csv`` and ``OUT/comparison.png`` (truth and
every method side by side at the middle truth frame).
"""

import contextlib
import csv
import time

import numpy as np
import zarr

from pipeline.cluster import dask_client
from pipeline.images import write_image
from pipeline.reconstruct import ReconstructOptions, output_centres, reconstruct
from pipeline.spike_store import open_spike_store
from pipeline.storage import resolve, zarr_store
from stages.errors import InputError
from stages.metrics import psnr, ssim
from stages.pictures import labelled, side_by_side

WINDOW = 41


def evaluate(store_url: str, methods: list[str], out_dir: str, *, weights: str | None = None,
             workers: int | None = None, scheduler: str | None = None, client=None, progress: bool = True) -> list[dict]:
    """Reconstruct with every method at the truth frames; return one summary row per method."""
    store = open_spike_store(store_url)
    if "truth" not in store.group or "truth_frames" not in store.group:
        raise InputError(f"{store_url} has no ground truth ('truth', 'truth_frames'): make one with cscsr simulate")
    truth, truth_frames = store.group["truth"], store.group["truth_frames"][:]
    every = int(store.attrs.get("truth_every", WINDOW))
    if list(truth_frames) != output_centres(store.n_frames, WINDOW, every)[: len(truth_frames)] or not len(truth_frames):
        raise InputError(f"{store_url}: truth frames {list(truth_frames)[:4]}... are not the 41-frame window centres 20, 20+{every}, ...")
    fs, root = resolve(out_dir)
    fs.makedirs(root, exist_ok=True)

    rows, per_frame, middle = [], [], len(truth_frames) // 2
    pictures = [labelled(truth[middle], f"truth (frame {truth_frames[middle]})")]
    with contextlib.nullcontext(client) if client else dask_client(workers=workers, scheduler=scheduler) as client:
        for method in methods:
            out = f"{str(out_dir).rstrip('/')}/{method}.zarr"
            start = time.perf_counter()
            reconstruct(store_url, out, ReconstructOptions(method=method, every=every, weights=weights, overwrite=True),
                        client=client, progress=progress)
            seconds = time.perf_counter() - start
            video = zarr.open_group(zarr_store(out, read_only=True), mode="r")["video"]
            scores = [(psnr(video[k], truth[k]), ssim(video[k], truth[k])) for k in range(len(truth_frames))]
            per_frame += [{"method": method, "frame": int(f), "psnr": p, "ssim": s} for f, (p, s) in zip(truth_frames, scores)]
            rows.append({"method": method, "psnr": float(np.mean([p for p, _ in scores])),
                         "ssim": float(np.mean([s for _, s in scores])), "frames": len(scores),
                         "seconds_per_image": seconds / len(scores)})
            pictures.append(labelled(video[middle], f"{method}: {scores[middle][0]:.2f} dB"))
    _write_csv(f"{root}/metrics.csv", fs, per_frame)
    _write_csv(f"{root}/summary.csv", fs, rows)
    write_image(f"{str(out_dir).rstrip('/')}/comparison.png", side_by_side(*pictures))
    return rows


def _write_csv(path: str, fs, rows: list[dict]) -> None:
    with fs.open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
