"""The batches a training run learns and is validated on, made from ``cscsr.training.training_data``'s clips.

Step ``n``'s batch comes from its own seed (``[seed, n, i]``), so a resumed run sees exactly the clips an
uninterrupted one would: simulated for its step (numpy), drawn from a pool simulated up front, or planned on
the CPU and synthesised on the device (``cscsr.training.synthesis``). ``_prefetch`` makes them in the background
while the network trains on the previous one; ``to_tensors`` puts one on the training device.
"""

import os

import numpy as np
import torch

from cscsr.training.training_data import (TRAIN_PICTURES, Clip, batch_arrays, check_not_test_pictures, picture_files,
                                 random_clip, random_plan, reoriented)
from cscsr.training.training_options import TrainOptions
from stages.prefetch import made_ahead


VALIDATION_SEED = 10_000_019  # validation clips: dead leaves from seeds no training step uses


def scale_of(step: int, options: TrainOptions) -> int:
    return 4 if np.random.default_rng([options.seed, step, 999]).random() < options.scale4_share else 2


def make_batch(step: int, options: TrainOptions, cache: dict, pool: dict | None = None,
               pictures: tuple = TRAIN_PICTURES):
    """Step ``step``'s batch: numpy arrays (``batch_arrays``), or for on-device synthesis the CPU's share of it
    (``cscsr.training.synthesis.PreparedBatch``, the same clips' plans)."""
    if options.distinct_batches:
        step = 1 + (step - 1) % options.distinct_batches
    scale = scale_of(step, options)
    mono = options.network().mono
    if options.on_device_synthesis:
        from cscsr.training.synthesis import prepare

        return prepare([random_plan([options.seed, step, i], lr_side=options.lr_side, scale=scale, pictures=pictures,
                                    cache=cache, dead_leaves_share=options.dead_leaves, mono=mono)
                          for i in range(options.batch)])
    if pool:
        rng = np.random.default_rng([options.seed, step, 998])
        clips = pool[scale]
        return batch_arrays([reoriented(clips[i], int(k)) for i, k in
                             zip(rng.integers(len(clips), size=options.batch), rng.integers(8, size=options.batch))])
    clips = [random_clip([options.seed, step, i], lr_side=options.lr_side, scale=scale, pictures=pictures,
                         cache=cache, dead_leaves_share=options.dead_leaves, mono=mono)
             for i in range(options.batch)]
    return batch_arrays(clips)


def clip_pool(options: TrainOptions) -> dict[int, list]:
    """``options.pool`` clips simulated once, by scale (the x4 share as in the steps), on every core.

    Simulating a clip costs about as much as a training step on it; a pool seen under eight
    orientations halves the time per step. Clip i comes from seed ``[seed, 997, i]``, so a resumed
    run rebuilds the same pool.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    fours = round(options.pool * options.scale4_share)
    scales = [4 if i < fours else 2 for i in range(options.pool)]
    pool: dict[int, list] = {2: [], 4: []}
    with ProcessPoolExecutor(os.cpu_count(), mp_context=multiprocessing.get_context("spawn")) as workers:
        mono = options.network().mono
        jobs = workers.map(_pool_clip, [([options.seed, 997, i], options.lr_side, s, mono) for i, s in enumerate(scales)],
                           chunksize=8)
        for clip in jobs:
            pool[clip.scale].append(clip)
    return pool


_WORKER_PICTURES: dict = {}  # a pool worker's decoded pictures, read once per process, not once per clip


def _pool_clip(args) -> Clip:
    seed, lr_side, scale, mono = args
    return random_clip(seed, lr_side=lr_side, scale=scale, pictures=TRAIN_PICTURES, cache=_WORKER_PICTURES, mono=mono)


def training_pictures(options: TrainOptions) -> tuple[str, ...]:
    """The pictures a run trains on: the files in ``options.pictures``'s folders (a folder of consecutive frames
    as one sequence, whose real motion makes the clips: ``cscsr.training.frame_motion``), else the bundled ones.

    Refused if any of them is a held-out test picture.
    """
    from cscsr.training.frame_motion import group_sequences

    folders = options.picture_folders()
    if not folders:
        return TRAIN_PICTURES
    names = picture_files(folders)
    check_not_test_pictures(names)
    return group_sequences(names)


def validation_batches(options: TrainOptions) -> list[dict]:
    """Fixed held-out clips at x4, alpha spread over [0.6, 1.0]; dead leaves only (no test pictures); mono for a
    mono network."""
    alphas = np.linspace(0.6, 1.0, options.validation_clips)
    mono = options.network().mono
    return [batch_arrays([random_clip([VALIDATION_SEED, i], lr_side=48, scale=4, pictures=(), alpha=float(a),
                                      mono=mono)])
            for i, a in enumerate(alphas)]


def to_tensors(batch, device: str = "cpu") -> dict:
    """A batch (numpy arrays, or a ``PreparedBatch`` to synthesise) as tensors on ``device``."""
    from cscsr.training.synthesis import PreparedBatch, synthesise

    if isinstance(batch, PreparedBatch):
        return synthesise(batch, device)
    arrays = {"spikes": torch.from_numpy(batch["spikes"]).float(), "truth": torch.from_numpy(batch["truth"]),
              "flows": torch.from_numpy(batch["flows"]), "zero_reset": torch.from_numpy(batch["zero_reset"]),
              "alpha": torch.from_numpy(batch["alpha"]).float()}
    return {**{k: v.to(device) for k, v in arrays.items()}, "cfa": batch["cfa"], "scale": batch["scale"]}


def _prefetch(step: int, options: TrainOptions, pool: dict | None = None,
              pictures: tuple = TRAIN_PICTURES, depth: int = 2):
    """Batches for steps step+1, step+2, ... made in the background, in order.

    On the CPU one thread (the cores train). With on-device synthesis the CPU's share of each batch
    (scene crops, dead leaves, plans, sensor draws: about 15 ms a clip, most of it Python) is spread
    over worker processes, so that the GIL does not hold back the GPU.
    """
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    if options.on_device_synthesis:
        processes = max(1, min(12, (os.cpu_count() or 1) - 2))
        workers = ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn"),
                                      initializer=_start_batch_worker, initargs=(options, pictures))
        make, ahead = _worker_batch, depth * processes
    else:
        cache: dict = {}
        workers = ThreadPoolExecutor(1, thread_name_prefix="batches")
        make, ahead = (lambda n: make_batch(n, options, cache, pool, pictures)), depth
    return made_ahead(make, range(step + 1, options.steps + 1), workers, ahead)


_WORKER: dict = {}  # a batch worker process's options, pictures and decoded-picture cache


def _start_batch_worker(options: TrainOptions, pictures: tuple) -> None:
    import cv2

    cv2.setNumThreads(1)
    torch.set_num_threads(1)
    _WORKER.update(options=options, pictures=pictures, cache={})


def _worker_batch(step: int):
    return make_batch(step, _WORKER["options"], _WORKER["cache"], None, _WORKER["pictures"])
