"""Acceptance on the bundled recordings: ingest, info, TFP against ground truth, export."""

import json

import cv2
import imageio.v3 as iio
import numpy as np

from cscsr import samples
from pipeline.jobs.preview import preview
from stages.measures.metrics import correlation


def test_reds_clip_ingests_matches_truth_and_exports_identically(cli, reds_dat, tmp_path):
    store = tmp_path / "reds.zarr"
    result = cli("ingest", reds_dat, store, "--height", 250, "--width", 400, "--flip", "--cfa", "mono")
    assert result.exit_code == 0, result.stderr

    info = json.loads(cli("info", store, "--json").stdout)
    assert (info["frames"], info["height"], info["width"], info["cfa"]) == (301, 250, 400, "mono")
    assert abs(info["firing_rate"] - 0.2877) < 5e-4  # the sample README's mean rate
    assert info["state"] == "complete" and info["bits_per_pixel"] < 1.0
    assert "301" in cli("info", store).stdout  # the human table shows it too

    shot = preview(str(store), centre=151, window=41, gain=1 / 0.6)  # frames 130..170
    truth = iio.imread(samples.path(samples.REDS_GT))
    assert shot.image.shape == (250, 400, 3)
    assert correlation(shot.image, truth) >= 0.98
    assert abs(shot.image[:, :, 0].mean() - truth.mean()) < 1.0

    exported = tmp_path / "back.dat"
    assert cli("export", store, exported).exit_code == 0
    assert exported.read_bytes() == open(reds_dat, "rb").read()


def test_reds_clip_without_flip_does_not_match(cli, reds_dat, tmp_path):
    """The correlation test above can fail: the unflipped clip does not match its truth."""
    store = tmp_path / "upside_down.zarr"
    assert cli("ingest", reds_dat, store, "--height", 250, "--width", 400).exit_code == 0
    shot = preview(str(store), centre=151, gain=1 / 0.6)
    assert correlation(shot.image, iio.imread(samples.path(samples.REDS_GT))) < 0.2


def test_real_helicopter_shows_structure(cli, helicopter_npz, tmp_path):
    store, picture = tmp_path / "heli.zarr", tmp_path / "helicopter.png"
    assert cli("ingest", helicopter_npz, store).exit_code == 0
    info = json.loads(cli("info", store, "--json").stdout)
    assert (info["frames"], info["height"], info["width"]) == (200, 250, 250)
    assert abs(info["firing_rate"] - 0.0314) < 5e-4

    assert cli("preview", store, picture, "--window", 199).exit_code == 0
    image = iio.imread(picture)[:, :, 0].astype(np.float64)
    assert image.std() > 10  # auto exposure gives a usable picture

    # A picture has spatial structure: it agrees with a blurred copy of itself far more
    # than the same pixels shuffled do (shot noise alone would give neither).
    blurred = cv2.GaussianBlur(image, (0, 0), 3)
    shuffled = np.random.default_rng(0).permutation(image.ravel()).reshape(image.shape)
    assert correlation(image, blurred) > 0.7
    assert correlation(shuffled, cv2.GaussianBlur(shuffled, (0, 0), 3)) < 0.2
    # The display (Caltech-101 image) is brighter than the dark border around it.
    assert image[60:190, 30:220].mean() > 1.4 * image[:15].mean()  # measured ratio: 1.78
