"""``cscsr demo``: ingest the bundled recordings, look at them, export, and report known answers."""

import hashlib
import os

from rich.console import Console
from rich.table import Table

from cscsr import samples
from pipeline.export import export
from pipeline.images import read_image, write_image
from pipeline.info import summarize
from pipeline.ingest import IngestOptions, ingest
from pipeline.preview import preview
from stages.metrics import correlation, psnr, side_by_side


def _sha256(path: str) -> str:
    with open(path, "rb") as handle:
        return hashlib.file_digest(handle, "sha256").hexdigest()


def run(out_dir: str, *, console: Console) -> dict:
    """Run the demo into ``out_dir`` (replacing earlier demo outputs); return its figures."""
    os.makedirs(out_dir, exist_ok=True)
    reds, heli = os.path.join(out_dir, "reds.zarr"), os.path.join(out_dir, "helicopter.zarr")
    dat = samples.path(samples.REDS_DAT)

    ingest(dat, reds, IngestOptions(samples.REDS_HEIGHT, samples.REDS_WIDTH, flip=True, overwrite=True))
    ingest(samples.path(samples.HELICOPTER_NPZ), heli, IngestOptions(overwrite=True))

    shot = preview(reds, centre=samples.REDS_KEY_FRAME, gain=samples.REDS_GAIN)
    truth = read_image(samples.path(samples.REDS_GT))
    write_image(os.path.join(out_dir, "reds_tfp_vs_truth.png"), side_by_side(shot.image, truth))
    heli_shot = preview(heli, window=199)  # ~0.03 spikes/pixel/frame: a long window tames shot noise
    write_image(os.path.join(out_dir, "helicopter_tfp.png"), heli_shot.image)

    round_trip = os.path.join(out_dir, "reds_roundtrip.dat")
    export(reds, round_trip, overwrite=True)

    figures = {
        "REDS clip: TFP vs ground truth, correlation": correlation(shot.image, truth),
        "REDS clip: TFP vs ground truth, PSNR (dB)": psnr(shot.image[:, :, 0], truth),
        "REDS clip: stored bits/pixel": summarize(reds)["bits_per_pixel"],
        "REDS clip: export byte-identical to input": _sha256(round_trip) == _sha256(dat),
        "helicopter (real): firing rate": summarize(heli)["firing_rate"],
        "helicopter (real): auto gain": heli_shot.gain,
    }
    table = Table(title="cscsr demo (bundled samples)")
    table.add_column("figure")
    table.add_column("value", justify="right")
    for name, value in figures.items():
        table.add_row(name, f"{value:.4f}" if isinstance(value, float) else str(value))
    console.print(table)
    console.print(f"pictures: {out_dir}/reds_tfp_vs_truth.png (TFP | truth), {out_dir}/helicopter_tfp.png")
    return figures
