"""The bundled REDS ``.dat`` against its truth (docs/formats.md, Bundled samples): TFP, TFI and each mono weights
file at frame 151, PSNR and SSIM by scikit-image (``stages.measures.metrics``) against the 8-bit grey truth.

The clip (``cscsr/samples/``, mono, 301 frames of 250x400, stored upside down) is ingested as ``cscsr ingest
--height 250 --width 400 --flip`` does, then reconstructed as ``cscsr reconstruct --every 131 --gain 1/0.6`` does
(``--every 131`` puts an output frame at 151, made from the window of frames 131..171; the gain is the sample's
known answer): TFP and TFI at x1 and x2, the network (``--method cscsr --weights FILE``) at x2, its smaller scale.
An x2 picture is area-averaged back to 250x400 to meet the truth: the mean of each 2x2 block, scored as it is
(not rounded; rounded to 8 bits in the picture).

    python benchmarks/reds_quality.py [--weights FILE ...] [--work DIR] [--picture PATH] [--json]

``--weights`` (repeatable): default the shipped ``lite-mono``. ``--work``: where the store and the videos go
(default a temporary folder, removed after; a store already there is reused). ``--picture``: the truth, TFP and TFI
at x1 and the first weights file's network (x2 averaged back) side by side, each labelled with its PSNR, 8-bit grey
(docs/reds_methods.png is this picture with the shipped weights). Prints the markdown table; ``--json`` the same as
JSON. Under a minute for one weights file on 2 cores.
"""

import argparse
import json
import tempfile
from pathlib import Path

from _common import ROOT, markdown_table

EVERY = 131  # output frames at 20 and 151: the second is the truth's
SCALES = {"tfp": (1, 2), "tfi": (1, 2), "cscsr": (2,)}  # the network's smaller scale; it has no x1
LITE_MONO = ROOT / "cscsr" / "weights" / "cscsr-lite-mono.safetensors"


def averaged_back(image, scale: int):
    """(sH, sW) uint8 -> (H, W): the mean of each s x s block (area averaging), float64 (x1: the image as it is)."""
    import numpy as np

    if scale == 1:
        return image
    h, w = image.shape[0] // scale, image.shape[1] // scale
    return image[: h * scale, : w * scale].astype(np.float64).reshape(h, scale, w, scale).mean(axis=(1, 3))


def reds_store(work: Path) -> str:
    """The bundled ``.dat`` ingested into ``work`` (once: a later run with the same ``--work`` reuses it)."""
    from cscsr import samples
    from pipeline.jobs.ingest import IngestOptions, ingest

    store = work / "reds.zarr"
    if not store.exists():
        ingest(samples.path(samples.REDS_DAT), str(store),
               IngestOptions(samples.REDS_HEIGHT, samples.REDS_WIDTH, cfa="mono", flip=True), progress=False)
    return str(store)


def frame_151(store: str, out: Path, method: str, scale: int, weights: str | None, client):
    """``cscsr reconstruct STORE OUT --method M --scale S --every 131 --gain 1/0.6 [--weights W]``'s frame at the
    truth's frame, grey at the truth's size (:func:`averaged_back`)."""
    from cscsr import samples
    from pipeline.jobs.reconstruct import ReconstructOptions, reconstruct
    from pipeline.stores.video_store import FRAMES, VIDEO, open_video_store

    reconstruct(store, str(out), ReconstructOptions(method=method, scale=scale, every=EVERY, gain=samples.REDS_GAIN,
                                                    weights=weights, overwrite=True), client=client, progress=False)
    video = open_video_store(str(out))
    centres = list(video[FRAMES][:])
    frame = video[VIDEO][centres.index(samples.REDS_KEY_FRAME)]  # (sH, sW, 3), three equal channels: mono
    return averaged_back(frame[:, :, 0], scale)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--weights", action="append", help="a mono weights file (repeat; default lite-mono)")
    parser.add_argument("--work", help="where the store and the videos go (default: a temporary folder)")
    parser.add_argument("--picture", help="write the labelled truth | TFP | TFI | CSCSR picture here")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    args.weights = args.weights or [str(LITE_MONO)]

    from cscsr import samples
    from pipeline.compute.cluster import dask_client
    from pipeline.stores.images import read_image, write_image
    from stages.measures.metrics import psnr, ssim
    from stages.measures.montage import labelled, side_by_side
    from stages.reconstruction.methods import WINDOW

    truth = read_image(samples.path(samples.REDS_GT))  # (250, 400) grey
    with tempfile.TemporaryDirectory(prefix="cscsr-reds-quality-") as scratch:
        work = Path(args.work or scratch)
        work.mkdir(parents=True, exist_ok=True)
        store = reds_store(work)
        runs = [(method, scale, None) for method in ("tfp", "tfi") for scale in SCALES[method]]
        runs += [("cscsr", scale, weights) for weights in args.weights for scale in SCALES["cscsr"]]
        rows, pictures = [], {}
        with dask_client(workers=2) as client:
            for k, (method, scale, weights) in enumerate(runs):
                image = frame_151(store, work / f"{k}-{method}-x{scale}.zarr", method, scale, weights, client)
                label = method if weights is None else f"{method} {weights}"
                pictures[(method, scale, weights)] = image
                rows.append({"method": label, "scale": scale, "psnr": psnr(image, truth), "ssim": ssim(image, truth)})
    if args.picture:
        import numpy as np

        first = ("cscsr", SCALES["cscsr"][0], args.weights[0])
        panels = [(pictures[key], key[0]) for key in (("tfp", 1, None), ("tfi", 1, None), first)]
        picture = side_by_side(labelled(truth, f"truth (frame {samples.REDS_KEY_FRAME})"),
                               *[labelled(np.rint(image).astype(np.uint8), f"{name}  {psnr(image, truth):.2f} dB")
                                 for image, name in panels])
        write_image(args.picture, picture[:, :, 0])  # every panel grey: one channel
    if args.json:
        print(json.dumps(rows, indent=1))
        return
    half = WINDOW // 2
    print(f"REDS .dat, frame {samples.REDS_KEY_FRAME} (window {samples.REDS_KEY_FRAME - half}.."
          f"{samples.REDS_KEY_FRAME + half}, gain 1/0.6) against its truth, 250x400, grey")
    print(markdown_table(["method", "PSNR", "SSIM"],
                         [[f"{r['method']}, x{r['scale']}" + (" averaged back" if r["scale"] > 1 else ""),
                           f"{r['psnr']:.2f} dB", f"{r['ssim']:.3f}"] for r in rows]))
    if args.picture:
        print(f"picture: {args.picture}")


if __name__ == "__main__":
    main()
