"""``cscsr demo`` run for real (about 40 s on 2 cores): both networks in its table and picture, an mp4 of
seconds, labelled pictures, and the README showing exactly what it prints."""

import os
import re

import imageio.v3 as iio
import numpy as np
import pytest
from rich.console import Console

from cscsr import samples
from pipeline.demo import run
from pipeline.jobs.export import VIDEO_FPS
from pipeline.stores.images import read_image
from pipeline.jobs.preview import preview
from stages.measures.montage import side_by_side

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PANEL = 256  # HR pixels of the demo's scene


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("demo") / "demo-output")
    console = Console(record=True, width=100_000)  # no line is wrapped, however long the temporary path
    figures = run(out, console=console)
    return out, figures, console.export_text()


def _cells(row: str) -> list[str]:
    return [cell.strip() for cell in row.strip().strip("│|").split("│" if "│" in row else "|")]


def test_the_table_shows_both_networks(demo):
    _, figures, printed = demo
    assert [row["method"] for row in figures["methods"]] == ["tfp", "tfi", "cscsr lite", "cscsr full"]
    printed_rows = {_cells(line)[0]: _cells(line)[1:3] for line in printed.splitlines() if line.startswith("│")}
    for row in figures["methods"]:
        assert printed_rows[row["method"]] == [f"{row['psnr']:.4g}", f"{row['ssim']:.4g}"]
    psnrs = {row["method"]: row["psnr"] for row in figures["methods"]}
    assert psnrs["cscsr full"] > psnrs["cscsr lite"] > psnrs["tfi"] > psnrs["tfp"]


def test_the_video_lasts_seconds(demo):
    out, figures, printed = demo
    video = iio.imread(os.path.join(out, "video_cscsr.mp4"))
    assert video.shape[0] >= 3 * VIDEO_FPS and video.shape[1:] == (PANEL, PANEL, 3)
    assert np.abs(video[0].astype(float) - video[-1]).mean() > 5  # the camera moves
    assert figures["video_frames"] == video.shape[0]
    (line,) = [line for line in printed.splitlines() if line.startswith("pictures: ")]  # one logical line
    assert f"video_cscsr.mp4 (cscsr lite, {video.shape[0]} frames, {video.shape[0] / VIDEO_FPS:.1f} s)" in line


def _has_text(band: np.ndarray) -> bool:
    return (band < 128).any() and (band == 255).mean() > 0.5  # dark glyphs on a white band


def test_the_comparison_panels_are_labelled(demo):
    out, _, _ = demo
    comparison = read_image(os.path.join(out, "comparison.png"))
    panels = 5  # truth, tfp, tfi, cscsr lite, cscsr full
    assert comparison.shape[1] == panels * PANEL + (panels - 1) * 4
    band = comparison.shape[0] - PANEL
    assert band > 0
    for k in range(panels):
        assert _has_text(comparison[:band, k * (PANEL + 4): k * (PANEL + 4) + PANEL])


def test_the_reds_panels_are_labelled(demo):
    out, _, _ = demo
    reds = read_image(os.path.join(out, "reds_tfp_vs_truth.png"))
    shot = preview(os.path.join(out, "reds.zarr"), centre=samples.REDS_KEY_FRAME, gain=samples.REDS_GAIN)
    bare = side_by_side(shot.image, read_image(samples.path(samples.REDS_GT)))
    band = reds.shape[0] - bare.shape[0]
    assert band > 0 and reds.shape[1] == bare.shape[1]
    np.testing.assert_array_equal(reds[band:], bare)  # the pictures themselves, under their labels
    width = (bare.shape[1] - 4) // 2
    assert _has_text(reds[:band, :width]) and _has_text(reds[:band, width + 4:])


def test_the_readme_shows_what_the_demo_prints(demo):
    out, figures, printed = demo
    readme = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    table = readme.split("| method | PSNR (dB) | SSIM |", 1)[1].split("\n\n", 1)[0]
    shown = [_cells(line) for line in table.strip().splitlines()[1:]]
    assert shown == [[row["method"], f"{row['psnr']:.4g}", f"{row['ssim']:.4g}"] for row in figures["methods"]]
    prose = " ".join(readme.split())
    frames = iio.imread(os.path.join(out, "video_cscsr.mp4")).shape[0]
    assert re.search(rf"\b{frames / VIDEO_FPS:.1f} s mp4\b", prose) and f"{frames} frames" in prose
    key = "REDS .dat clip: TFP vs ground truth, "
    assert f"correlation {figures[key + 'correlation']:.3f}, PSNR {figures[key + 'PSNR (dB)']:.1f} dB" in prose

    picture = read_image(os.path.join(ROOT, "docs", "demo_comparison.png")).astype(float)
    made = read_image(os.path.join(out, "comparison.png")).astype(float)
    assert picture.shape == made.shape
    assert np.abs(picture - made).mean() < 0.05  # the same picture (a network's last bit may differ by CPU)
