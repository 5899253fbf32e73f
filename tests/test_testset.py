"""The held-out test set: regenerated bit for bit, kept apart from training, evaluated per alpha."""

import json

from pipeline.jobs.testset import ALPHAS, PICTURES, items, make_testset
from cscsr.training.training_data import TEST_PICTURES, TRAIN_PICTURES
from tests.test_simulate import chunk_files


def test_the_test_set_is_apart_from_training_and_covers_every_alpha():
    assert set(PICTURES) == set(TEST_PICTURES) and not set(PICTURES) & set(TRAIN_PICTURES)
    assert sorted({(i.picture, i.alpha) for i in items()}) == sorted((p, a) for p in PICTURES for a in ALPHAS)
    assert len({i.seed for i in items()}) == len(items())  # every item its own motion


def test_make_testset_regenerates_identical_bytes(tmp_path):
    one = make_testset(str(tmp_path / "one"), workers=2, progress=False, only=["coffee_a0.8"])
    two = make_testset(str(tmp_path / "two"), workers=1, progress=False, only=["coffee_a0.8"])
    a, b = chunk_files(one[0]), chunk_files(two[0])
    assert a.keys() == b.keys() and len(a) > 5
    assert all(a[name] == b[name] for name in a if name != "zarr.json")  # every array, chunk for chunk
    root_a, root_b = json.loads(a["zarr.json"]), json.loads(b["zarr.json"])
    assert root_a["attributes"].pop("source").endswith("one/sources/coffee.png")  # the only difference: where
    assert root_b["attributes"].pop("source").endswith("two/sources/coffee.png")
    assert root_a == root_b
    manifest = json.loads((tmp_path / "one" / "manifest.json").read_text())
    assert manifest["items"] == [{"picture": "coffee", "alpha": 0.8, "seed": 1011, "store": "coffee_a0.8.zarr"}]
    assert (tmp_path / "one" / "sources" / "coffee.png").read_bytes() == (tmp_path / "two" / "sources" / "coffee.png").read_bytes()


def test_evaluate_testset_writes_the_table_and_crops(tmp_path, cli):
    make_testset(str(tmp_path / "set"), workers=2, progress=False, only=["astronaut_a1.0"])
    result = cli("evaluate-testset", tmp_path / "set", "--methods", "tfp,tfi", "--out", tmp_path / "ev", "--workers", 2)
    assert result.exit_code == 0, result.stdout
    rows = (tmp_path / "ev" / "summary.csv").read_text().splitlines()
    assert rows[0] == "method,alpha,psnr,ssim,seconds_per_image" and len(rows) == 1 + 2 * 2  # (1.0, all) x 2 methods
    tfp = [float(r.split(",")[2]) for r in rows[1:] if r.startswith("tfp")]
    assert 15 < tfp[0] < 30 and tfp[0] == tfp[1]  # one alpha: its row is the mean
    assert (tmp_path / "ev" / "crops.png").stat().st_size > 1000
    assert cli("evaluate-testset", tmp_path, "--out", tmp_path / "x").exit_code == 1  # not a test set
