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

from pipeline.compute.cluster import check_in_memory, check_scheduler, check_workers, dask_client
from pipeline.stores.ground_truth import read_truth
from pipeline.stores.images import write_image
from pipeline.stores.outputs import EVALUATION, mark_folder, new_output
from pipeline.jobs.reconstruct import ReconstructOptions, checked_method, reconstruct
from pipeline.stores.spike_store import open_spike_store
from pipeline.stores.storage import check_apart, resolve
from pipeline.stores.video_store import VIDEO, open_video_store
from stages.errors import InputError
from stages.measures.metrics import psnr, ssim
from stages.reconstruction.methods import METHODS, NETWORKS, WINDOW, output_centres
from stages.measures.montage import labelled, side_by_side


def check_methods(methods: list[str], weights: str | None = None) -> None:
    """Refuse a ``--methods`` list that is empty, or names a method that does not exist or one twice, and
    ``--weights`` with no network among them, before any method runs."""
    if not methods:
        raise InputError(f"--methods is empty: give one or more of {', '.join(METHODS)}, separated by commas")
    for index, method in enumerate(methods):
        if method not in METHODS:
            raise InputError(f"--methods: unknown method {method!r}: expected one of {', '.join(METHODS)}")
        if method in methods[:index]:
            raise InputError(f"--methods names {method} twice")
    if weights is not None and not set(methods) & set(NETWORKS):
        raise InputError(f"--weights is for the network (cscsr or cscsr-ensemble in --methods); {', '.join(methods)} "
                         f"have no weights to load: leave --weights out")


def checked_evaluation(store_url: str, methods: list[str], weights: str | None) -> tuple:
    """Every check of an evaluation that needs no output: the store's truth, and every method's options
    and weights against it. -> (store, truth frames, options per method)."""
    check_methods(methods, weights)
    store = open_spike_store(store_url)
    _, truth_frames = read_truth(store)
    every = int(store.attrs.get("truth_every", WINDOW))
    if list(truth_frames) != output_centres(store.n_frames, WINDOW, every)[: len(truth_frames)] or not len(truth_frames):
        raise InputError(f"{store_url}: truth frames {list(truth_frames)[:4]}... are not the 41-frame window centres 20, 20+{every}, ...")
    options = {method: ReconstructOptions(method=method, every=every, weights=weights if method in NETWORKS else None)
               for method in methods}  # into OUT, claimed new by evaluate: never over an existing store
    for method in methods:
        checked_method(store, options[method])
    return store, truth_frames, options


def evaluate(store_url: str, methods: list[str], out_dir: str, *, weights: str | None = None,
             workers: int | None = None, scheduler: str | None = None, client=None, progress: bool = True,
             overwrite: bool = False) -> list[dict]:
    """Reconstruct with every method at the truth frames; return one summary row per method.

    ``out_dir`` is a new output: an existing one is refused unless ``overwrite`` (and it is an evaluation),
    and a failed evaluation leaves none."""
    check_apart(out_dir, store_url, weights)
    check_workers(workers)
    check_in_memory((store_url, out_dir, weights), client=client)  # the reconstructions' tasks read and write them
    store, truth_frames, options = checked_evaluation(store_url, methods, weights)
    if client is None:
        check_scheduler(scheduler)  # a named scheduler answers (within seconds) before OUT exists
    with new_output(out_dir, overwrite=overwrite, kind=EVALUATION):
        mark_folder(out_dir, EVALUATION)
        return _evaluate(store_url, store, truth_frames, options, methods, out_dir, workers=workers,
                         scheduler=scheduler, client=client, progress=progress)


def _evaluate(store_url: str, store, truth_frames, options: dict, methods: list[str], out_dir: str, *,
              workers: int | None, scheduler: str | None, client, progress: bool) -> list[dict]:
    truth, _ = read_truth(store)
    fs, root = resolve(out_dir)

    rows, per_frame, videos = [], [], {}
    with contextlib.nullcontext(client) if client else dask_client(workers=workers, scheduler=scheduler) as client:
        for method in methods:
            out = f"{str(out_dir).rstrip('/')}/{method}.zarr"
            start = time.perf_counter()
            reconstruct(store_url, out, options[method], client=client, progress=progress)
            seconds = time.perf_counter() - start
            video = open_video_store(out)[VIDEO]
            scores = [(psnr(video[k], truth[k]), ssim(video[k], truth[k])) for k in range(len(truth_frames))]
            per_frame += [{"method": method, "frame": int(f), "psnr": p, "ssim": s} for f, (p, s) in zip(truth_frames, scores)]
            rows.append({"method": method, "psnr": float(np.mean([p for p, _ in scores])),
                         "ssim": float(np.mean([s for _, s in scores])), "frames": len(scores),
                         "seconds_per_image": seconds / len(scores)})
            videos[method] = video
    _write_csv(f"{root}/metrics.csv", fs, per_frame)
    _write_csv(f"{root}/summary.csv", fs, rows)
    write_image(f"{str(out_dir).rstrip('/')}/comparison.png", comparison_picture(truth, truth_frames, videos))
    return rows


def comparison_picture(truth, truth_frames, videos: dict) -> np.ndarray:
    """The truth and every video side by side at the middle truth frame, each under its label and its PSNR
    there (``videos``: label -> frames at the truth frames, as a video store holds them)."""
    middle = len(truth_frames) // 2
    pictures = [labelled(truth[middle], f"truth (frame {truth_frames[middle]})")]
    pictures += [labelled(video[middle], f"{label}: {psnr(video[middle], truth[middle]):.2f} dB this frame")
                 for label, video in videos.items()]
    return side_by_side(*pictures)


def _write_csv(path: str, fs, rows: list[dict]) -> None:
    with fs.open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
