"""``cscsr evaluate``: methods against a simulated store's ground truth, as numbers and pictures.

Each method runs through the same distributed reconstruction as ``cscsr reconstruct``, at
exactly the store's truth frames (window 41, one output every ``truth_every`` frames), into
``OUT/<method>.zarr``. PSNR and SSIM come from scikit-image. Writes ``OUT/metrics.csv``
(one row per method and frame), ``OUT/summary.csv`` and ``OUT/comparison.png`` (truth and
every method side by side at the middle truth frame). Written videos (``--video NAME=URL``: your own method's, e.g.
``cscsr.lazy.to_video``) are read, not run, and scored alike beside the methods.
"""

import contextlib
import csv
import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from pipeline.compute.cluster import check_in_memory, check_scheduler, check_workers, dask_client
from pipeline.stores.ground_truth import read_truth
from pipeline.stores.images import write_image
from pipeline.stores.outputs import EVALUATION, mark_folder, new_output
from pipeline.jobs.reconstruct import ReconstructOptions, checked_method, reconstruct
from pipeline.stores.spike_store import open_spike_store, store_identity
from pipeline.stores.storage import check_apart, resolve
from pipeline.stores.video_store import FRAMES, VIDEO, lost_frames, open_video_store
from stages.errors import InputError
from stages.measures.metrics import SSIM_SIDE, psnr, ssim
from stages.reconstruction.methods import METHODS, NETWORKS, WINDOW, output_centres
from stages.measures.montage import labelled, side_by_side

SCORING_THREADS = 4  # frames scored at once, at most (each of 4000x4000 holds about 2.5 GB of SSIM's arrays)


def check_methods(methods: list[str], weights: str | None = None, videos: dict | None = None) -> None:
    """Refuse a ``--methods`` list that is empty (with no ``--video`` to score), or names a method that does not
    exist or one twice, and ``--weights`` with no network among them, before any method runs."""
    if not methods and not videos:
        raise InputError(f"--methods is empty: give one or more of {', '.join(METHODS)}, separated by commas")
    for index, method in enumerate(methods):
        if method not in METHODS:
            raise InputError(f"--methods: unknown method {method!r}: expected one of {', '.join(METHODS)}")
        if method in methods[:index]:
            raise InputError(f"--methods names {method} twice")
    if weights is not None and not set(methods) & set(NETWORKS):
        raise InputError(f"--weights is for the network (cscsr or cscsr-ensemble in --methods); {', '.join(methods)} "
                         f"{'has' if len(methods) == 1 else 'have'} no weights to load: leave --weights out")


def parse_videos(texts: list[str] | None) -> dict[str, str]:
    """``--video NAME=URL`` (repeatable) -> {NAME: URL}; one line for a text without ``=`` or a name given twice."""
    videos: dict[str, str] = {}
    for text in texts or []:
        name, sign, url = text.partition("=")
        if not sign or not name.strip() or not url.strip():
            raise InputError(f"--video {text!r}: give NAME=URL (a name for the table, a video store's path or URL)")
        if name.strip() in videos:
            raise InputError(f"--video names {name.strip()} twice")
        videos[name.strip()] = url.strip()
    return videos


def checked_videos(videos: dict, store, truth, truth_frames, methods: list[str]) -> dict[str, tuple]:
    """Every ``--video NAME=URL`` checked against the store's truth before anything is written: a name of its own
    (not a method's, not empty), a complete video store made from this recording (where it records its source),
    holding every truth frame, at the truth's scale (a ``region`` is scored against that part of the truth).
    -> {name: (video array, the index of each truth frame in it, (y0, y1, x0, x1) of the truth it covers)}."""
    if not isinstance(videos, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in videos.items()):
        raise InputError(f"videos must map names to video store URLs ({{'mine': 'mine.zarr'}}), got {videos!r}")
    checked = {}
    for name, url in videos.items():
        if not name.strip() or "," in name or name in methods:
            raise InputError(f"--video {name}={url}: give it a name of its own (not empty, no comma, not one of "
                             f"--methods)")
        group = open_video_store(url)
        attrs = dict(group.attrs)
        if attrs.get("state") != "complete":
            raise InputError(f"--video {name}={url} is incomplete (state {attrs.get('state')!r}): finish it first")
        if lost := lost_frames(group):  # as lazy.open_video refuses it: a lost chunk would be scored as black
            raise InputError(f"--video {name}={url} has lost data: {lost}: make it again")
        if attrs.get("source_identity") not in (None, store_identity(store)):
            raise InputError(f"--video {name}={url} was made from another recording (source {attrs.get('source')}), "
                             f"not {store.url}")
        frames, video = group[FRAMES][:], group[VIDEO]
        present = np.isin(truth_frames, frames)
        if not present.all():
            missing = [int(f) for f in np.asarray(truth_frames)[~present]]
            raise InputError(f"--video {name}={url} lacks the truth's frames {missing[:4]}...: reconstruct every "
                             f"{int(store.attrs.get('truth_every', WINDOW))} frames with window {WINDOW} (the truth's)")
        at = np.searchsorted(frames, truth_frames)
        height, width = truth.shape[1:3]
        scale, truth_scale = attrs.get("scale"), height // store.shape[1]  # the truth: the store's frames x scale
        if isinstance(scale, int) and scale != truth_scale:  # else its crop "fits" in a corner of the truth
            raise InputError(f"--video {name}={url} is at scale {scale}, and the truth at scale {truth_scale} "
                             f"({height}x{width} HR): give a video at the truth's scale (--scale {truth_scale})")
        region = attrs.get("region") or [0, store.shape[1], 0, store.shape[2]]
        crop = [side * scale for side in region] if isinstance(scale, int) else [0, height, 0, width]
        if video.shape[1:3] != (crop[1] - crop[0], crop[3] - crop[2]) or crop[1] > height or crop[3] > width:
            raise InputError(f"--video {name}={url} is {video.shape[1]}x{video.shape[2]} HR at scale "
                             f"{scale}, region {region}; the truth is {height}x{width}: give a video at the truth's "
                             f"scale")
        if min(video.shape[1:3]) < SSIM_SIDE:
            raise InputError(f"--video {name}={url} is {video.shape[1]}x{video.shape[2]} HR, smaller than SSIM's "
                             f"{SSIM_SIDE}x{SSIM_SIDE} window: give a larger region")
        checked[name] = (video, at, tuple(crop))
    return checked


def checked_evaluation(store_url: str, methods: list[str], weights: str | None, videos: dict | None = None) -> tuple:
    """Every check of an evaluation that needs no output (:func:`_checked_evaluation`), for a caller that only
    checks (``evaluate-testset``, before its output). -> (store, truth frames, options per method)."""
    store, _, truth_frames, options = _checked_evaluation(store_url, methods, weights, videos)
    return store, truth_frames, options


def _checked_evaluation(store_url: str, methods: list[str], weights: str | None, videos: dict | None = None) -> tuple:
    """Every check of an evaluation that needs no output: the store's truth, and every method's options
    and weights against it. -> (store, truth, truth frames, options per method): the truth read here once,
    for the checks of the videos and the scores."""
    check_methods(methods, weights, videos)
    store = open_spike_store(store_url)
    truth, truth_frames = read_truth(store)
    every = int(store.attrs.get("truth_every", WINDOW))
    if list(truth_frames) != output_centres(store.n_frames, WINDOW, every)[: len(truth_frames)] or not len(truth_frames):
        raise InputError(f"{store_url}: truth frames {list(truth_frames)[:4]}... are not the {WINDOW}-frame window centres {WINDOW // 2}, {WINDOW // 2}+{every}, ...")
    if min(truth.shape[1:3]) < SSIM_SIDE:  # scikit-image's own error came after every reconstruction
        raise InputError(f"{store_url}: its truth frames are {truth.shape[1]}x{truth.shape[2]} HR pixels, smaller than "
                         f"SSIM's {SSIM_SIDE}x{SSIM_SIDE} window: evaluate scores frames of at least that size")
    options = {method: ReconstructOptions(method=method, every=every, weights=weights if method in NETWORKS else None)
               for method in methods}  # into OUT, claimed new by evaluate: never over an existing store
    for method in methods:
        checked_method(store, options[method])
    return store, truth, truth_frames, options


def evaluate(store_url: str, methods: list[str], out_dir: str, *, weights: str | None = None,
             workers: int | None = None, scheduler: str | None = None, client=None, progress: bool = True,
             overwrite: bool = False, videos: dict[str, str] | None = None) -> list[dict]:
    """Reconstruct with every method at the truth frames; return one summary row per method, then one per written
    video of ``videos`` (name -> URL: your own method's output, e.g. ``cscsr.lazy.to_video``), scored alike at
    the truth frames (its ``seconds_per_image`` None: not timed here).

    ``out_dir`` is a new output: an existing one is refused unless ``overwrite`` (and it is an evaluation),
    and a failed evaluation leaves none."""
    videos = {} if videos is None else videos
    check_apart(out_dir, store_url, weights, *(videos.values() if isinstance(videos, dict) else ()))
    check_workers(workers, scheduler)
    check_in_memory((store_url, out_dir, weights), client=client)  # the reconstructions' tasks read and write them
    store, truth, truth_frames, options = _checked_evaluation(store_url, methods, weights, videos)
    written = checked_videos(videos, store, truth, truth_frames, methods)
    if client is None:
        check_scheduler(scheduler)  # a named scheduler answers (within seconds) before OUT exists
    with new_output(out_dir, overwrite=overwrite, kind=EVALUATION):
        mark_folder(out_dir, EVALUATION)
        return _evaluate(store_url, truth, truth_frames, options, methods, out_dir, workers=workers,
                         scheduler=scheduler, client=client, progress=progress, written=written)


def _evaluate(store_url: str, truth, truth_frames, options: dict, methods: list[str], out_dir: str, *,
              workers: int | None, scheduler: str | None, client, progress: bool, written: dict) -> list[dict]:
    """Score the written videos (read, nothing to run: before any method runs), then reconstruct and score every
    method, each by :func:`_scored`; write the CSVs and the picture, and return the summary rows, in the order the
    user reads them: the methods, then the videos."""
    fs, root = resolve(out_dir)
    whole = (0, truth.shape[1], 0, truth.shape[2])  # (y0, y1, x0, x1): a method's output covers all the truth
    scores, shown = {}, {}  # name -> (its summary row, its rows per frame); name -> its frames for the picture
    for name, (video, at, crop) in written.items():
        frames = [video[int(i)] for i in at]
        scores[name] = _scored(name, frames, truth, truth_frames, crop, seconds=None)
        shown[name] = _in_frame(frames, truth.shape[1:3], (crop[0], crop[2]))
    with contextlib.nullcontext(client) if client else dask_client(workers=workers, scheduler=scheduler) as client:
        for method in methods:
            out = f"{str(out_dir).rstrip('/')}/{method}.zarr"
            start = time.perf_counter()
            reconstruct(store_url, out, options[method], client=client, progress=progress)
            seconds = time.perf_counter() - start
            video = open_video_store(out)[VIDEO]
            scores[method] = _scored(method, video, truth, truth_frames, whole, seconds=seconds)
            shown[method] = video
    names = [*methods, *written]
    rows = [scores[name][0] for name in names]
    _write_csv(f"{root}/metrics.csv", fs, [row for name in names for row in scores[name][1]])
    _write_csv(f"{root}/summary.csv", fs, rows)
    write_image(f"{str(out_dir).rstrip('/')}/comparison.png",
                comparison_picture(truth, truth_frames, {name: shown[name] for name in names},
                                   {name: scores[name][1][len(truth_frames) // 2]["psnr"] for name in names}))
    return rows


def _scored(name: str, frames, truth, truth_frames, crop: tuple[int, int, int, int],
           seconds: float | None) -> tuple[dict, list[dict]]:
    """One video's scores against the truth, a method's and a written video's alike: ``frames`` at the truth
    frames (frame ``k`` at ``truth_frames[k]``; a method's video may hold more after them), of the part ``crop``
    (y0, y1, x0, x1) of the truth, made in ``seconds`` (None: not timed here). -> (its summary row, its rows per
    frame)."""
    y0, y1, x0, x1 = crop

    def scores(k: int) -> tuple[float, float]:  # each truth frame read once
        frame, truth_part = frames[k], truth[k][y0:y1, x0:x1]
        return psnr(frame, truth_part), ssim(frame, truth_part)

    # a frame a core (SSIM's filters let go of the GIL): at 4000x4000 the scores took 97 % of an evaluation, one
    # frame at a time; the same numbers, each frame's its own
    with ThreadPoolExecutor(min(SCORING_THREADS, os.cpu_count() or 1)) as pool:
        pairs = list(pool.map(scores, range(len(truth_frames))))
    per_frame = [{"method": name, "frame": int(f), "psnr": p, "ssim": s} for f, (p, s) in zip(truth_frames, pairs)]
    row = {"method": name, "psnr": float(np.mean([p for p, _ in pairs])), "ssim": float(np.mean([s for _, s in pairs])),
           "frames": len(pairs), "seconds_per_image": None if seconds is None else seconds / len(pairs)}
    return row, per_frame


def _in_frame(frames: list[np.ndarray], size: tuple[int, int], origin: tuple[int, int]) -> list[np.ndarray]:
    """Frames of a part of the picture (a video's ``region``) placed where they belong in black frames of ``size``:
    pictures side by side at one size."""
    if frames and frames[0].shape[:2] == tuple(size):
        return frames
    placed = []
    for frame in frames:
        whole = np.zeros((*size, 3), np.uint8)
        whole[origin[0]:origin[0] + frame.shape[0], origin[1]:origin[1] + frame.shape[1]] = frame
        placed.append(whole)
    return placed


def comparison_picture(truth, truth_frames, videos: dict, scored: dict | None = None) -> np.ndarray:
    """The truth and every video side by side at the middle truth frame, each under its label and its PSNR
    there (``videos``: label -> frames at the truth frames, as a video store holds them; ``scored``: label -> its
    PSNR there where it is not the whole frame's, a region's as ``metrics.csv`` has it)."""
    middle = len(truth_frames) // 2
    scored = scored or {}
    pictures = [labelled(truth[middle], f"truth (frame {truth_frames[middle]})")]
    pictures += [labelled(video[middle], f"{label}: "
                          f"{scored.get(label, psnr(video[middle], truth[middle])):.2f} dB this frame")
                 for label, video in videos.items()]
    return side_by_side(*pictures)


def _write_csv(path: str, fs, rows: list[dict]) -> None:
    with fs.open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
