"""``cscsr demo``: the main job on bundled data, start to finish.

1. Simulate a colour spike recording (RGGB, x4, a moving camera, ground truth) from a
   picture bundled with scikit-image, on a 2-worker local Dask cluster.
2. Reconstruct it with every method (the classic TFP and TFI, and the CSCSR network with
   both its shipped weights, ``lite`` and ``full``) on one cluster at the truth frames, write the
   HR video stores and a labelled side-by-side picture, and print PSNR / SSIM against the truth;
   then the network's (``lite``) video every ``VIDEO_EVERY`` spike frames, exported as an mp4 of
   a few seconds.
3. Check the bundled real-format samples: a raw ``.dat`` clip ingested, compared with its
   ground truth (a labelled picture) and exported back byte for byte; a real (mono) recording turned
   into a picture, and one window of it through the mono network beside TFP of the same frames.
"""

import hashlib
import os

import cv2
from rich.console import Console
from rich.table import Table
from skimage import data

from cscsr import samples
from pipeline.compute.cluster import dask_client
from pipeline.jobs.evaluate import comparison_picture, evaluate
from pipeline.jobs.export import VIDEO_FPS, export
from pipeline.stores.ground_truth import read_truth
from pipeline.stores.images import read_image, write_image
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.jobs.preview import preview
from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
from pipeline.jobs.simulate import SimulateOptions, simulate
from pipeline.stores.spike_store import open_spike_store
from pipeline.stores.storage import check_apart
from pipeline.stores.video_store import VIDEO, open_video_store
from stages.reconstruction.methods import NETWORKS, WINDOW
from stages.measures.metrics import correlation, psnr
from stages.measures.montage import labelled, side_by_side

# the table's rows and the picture's columns, by evaluation: (folder, its network's weights, methods);
# a network is labelled with its weights ("cscsr lite", "cscsr full")
EVALUATIONS = [("evaluation", "lite", ["tfp", "tfi", "cscsr"]), ("evaluation-full", "full", ["cscsr"])]
SCENE_SIZE = 256  # HR pixels: LR 64x64 at x4
FRAMES = 5 * WINDOW  # spike frames simulated: 5 truth frames, one per 41-frame window
VIDEO_EVERY = 5  # spike frames between the mp4's frames: 33 frames, 3.3 s at 10 fps (lite: ~0.5 s each on 2 cores)
HELICOPTER_CENTRE, HELICOPTER_SCALE = 100, 2  # the real recording's middle window, at the network's smaller scale


def _sha256(path: str) -> str:
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def _table(title: str, columns: list[str], rows: list[list]) -> Table:
    table = Table(title=title)
    for i, column in enumerate(columns):
        table.add_column(column, justify="left" if i == 0 else "right")
    for row in rows:
        table.add_row(*[f"{v:.4g}" if isinstance(v, float) else str(v) for v in row])
    return table


def simulated_job(out_dir: str, console: Console, workers: int) -> list[dict]:
    scene = os.path.join(out_dir, "scene.png")
    write_image(scene, cv2.resize(data.astronaut(), (SCENE_SIZE, SCENE_SIZE), interpolation=cv2.INTER_AREA))
    recording = os.path.join(out_dir, "recording.zarr")
    console.print(f"simulating {recording} from {scene} ...")
    simulate(scene, recording, SimulateOptions(scale=4, cfa="rggb", frames=FRAMES, motion="random", speed=0.3,
                                               reset="zero", truth_every=WINDOW, seed=0, overwrite=True), workers=workers)
    rows, videos = [], {}
    with dask_client(workers=workers) as client:  # one cluster for every network run below
        for folder, weights, methods in EVALUATIONS:
            found = evaluate(recording, methods, os.path.join(out_dir, folder), weights=weights, client=client,
                             overwrite=True)
            for method, row in zip(methods, found):
                label = f"{method} {weights}" if method in NETWORKS else method
                rows.append({**row, "method": label})
                videos[label] = open_video_store(os.path.join(out_dir, folder, f"{method}.zarr"))[VIDEO]
        video = os.path.join(out_dir, "video_cscsr.zarr")
        reconstruct(recording, video, ReconstructOptions(method="cscsr", every=VIDEO_EVERY, weights="lite",
                                                         overwrite=True), client=client)
    export(video, os.path.join(out_dir, "video_cscsr.mp4"), overwrite=True)
    truth, truth_frames = read_truth(open_spike_store(recording))
    write_image(os.path.join(out_dir, "comparison.png"), comparison_picture(truth, truth_frames, videos))
    console.print(_table(f"reconstruction x4 of {recording} against ground truth: means over {rows[0]['frames']} "
                         f"frames (comparison.png's panels: the PSNR of its one frame)",
                         ["method", "mean PSNR (dB)", "mean SSIM", "s / image"],
                         [[r["method"], r["psnr"], r["ssim"], r["seconds_per_image"]] for r in rows]))
    return rows


def sample_checks(out_dir: str, console: Console) -> dict:
    reds, heli = os.path.join(out_dir, "reds.zarr"), os.path.join(out_dir, "helicopter.zarr")
    dat = samples.path(samples.REDS_DAT)
    ingest(dat, reds, IngestOptions(samples.REDS_HEIGHT, samples.REDS_WIDTH, flip=True, overwrite=True), progress=False)
    ingest(samples.path(samples.HELICOPTER_NPZ), heli, IngestOptions(overwrite=True), progress=False)
    shot = preview(reds, centre=samples.REDS_KEY_FRAME, gain=samples.REDS_GAIN)
    truth = read_image(samples.path(samples.REDS_GT))
    write_image(os.path.join(out_dir, "reds_tfp_vs_truth.png"),
                side_by_side(labelled(shot.image, f"TFP (frame {shot.centre}, {shot.window}-frame window)"),
                             labelled(truth, "ground truth")))
    heli_shot = preview(heli, window=199)  # ~0.03 spikes/pixel/frame: a long window tames shot noise
    write_image(os.path.join(out_dir, "helicopter_tfp.png"), heli_shot.image)
    write_image(os.path.join(out_dir, "helicopter_tfp_vs_cscsr.png"), helicopter_through_the_network(heli, heli_shot.gain))
    round_trip = os.path.join(out_dir, "reds_roundtrip.dat")
    export(reds, round_trip, overwrite=True, progress=False)
    figures = {
        "REDS .dat clip: TFP vs ground truth, correlation": correlation(shot.image, truth),
        "REDS .dat clip: TFP vs ground truth, PSNR (dB)": psnr(shot.image[:, :, 0], truth),
        "REDS .dat clip: export byte-identical to input": _sha256(round_trip) == _sha256(dat),
        "real helicopter recording: auto gain": heli_shot.gain,
    }
    console.print(_table("bundled real-format samples", ["check", "value"], [[k, v] for k, v in figures.items()]))
    return figures


def helicopter_through_the_network(heli: str, gain: float):
    """One 41-frame window of the real mono helicopter recording at x2: TFP beside the mono network (``lite-mono``,
    the default for a mono recording), the same frames and gain, labelled. One window in this process: seconds."""
    from pipeline.jobs.reconstruct import reconstructor
    from stages.reconstruction.methods import Window

    store = open_spike_store(heli)
    half = WINDOW // 2
    window = Window(store.read(HELICOPTER_CENTRE - half, HELICOPTER_CENTRE + half + 1), store.meta.width,
                    store.meta.cfa, store.meta.reset, gain, HELICOPTER_SCALE)
    panels = [(reconstructor("tfp", None), "TFP"), (reconstructor("cscsr", "lite-mono"), "CSCSR lite-mono")]
    return side_by_side(*[labelled(method(window), f"{name}, frames {HELICOPTER_CENTRE - half}..{HELICOPTER_CENTRE + half}, "
                                                   f"x{HELICOPTER_SCALE}") for method, name in panels])


def run(out_dir: str, *, console: Console, workers: int = 2) -> dict:
    """Run the demo into ``out_dir`` (replacing earlier demo outputs); return its figures."""
    check_apart(out_dir, *(samples.path(name) for name in (samples.REDS_DAT, samples.REDS_GT, samples.HELICOPTER_NPZ)))
    os.makedirs(out_dir, exist_ok=True)
    rows = simulated_job(out_dir, console, workers)
    figures = sample_checks(out_dir, console)
    frames = open_video_store(os.path.join(out_dir, "video_cscsr.zarr"))[VIDEO].shape[0]
    console.print(f"pictures: {out_dir}/comparison.png (truth | {' | '.join(row['method'] for row in rows)}), "
                  f"{out_dir}/video_cscsr.mp4 (cscsr lite, {frames} frames, {frames / VIDEO_FPS:.1f} s), "
                  f"{out_dir}/reds_tfp_vs_truth.png, {out_dir}/helicopter_tfp.png, "
                  f"{out_dir}/helicopter_tfp_vs_cscsr.png")
    return {"methods": rows, **figures, "video_frames": frames}
