"""Spike stores and captures at any fsspec URL: path, file://, memory://, and s3:// (moto)."""

import fsspec

from pipeline.jobs.export import export
from pipeline.jobs.info import summarize
from pipeline.jobs.ingest import IngestOptions, ingest

REDS = IngestOptions(250, 400, flip=True)


def round_trip(src: str, store: str, dat: str) -> bytes:
    ingest(src, store, REDS, progress=False)
    assert summarize(store)["frames"] == 301
    export(store, dat, progress=False)
    fs, path = fsspec.core.url_to_fs(dat)
    return fs.cat_file(path)


def test_local_path_and_file_url(reds_dat, tmp_path):
    original = open(reds_dat, "rb").read()
    assert round_trip(reds_dat, str(tmp_path / "a.zarr"), str(tmp_path / "a.dat")) == original
    assert round_trip(f"file://{reds_dat}", f"file://{tmp_path}/new/dir/b.zarr", f"file://{tmp_path}/b.dat") == original


def test_memory_url(reds_dat):
    original = open(reds_dat, "rb").read()
    assert round_trip(reds_dat, "memory://urls/reds.zarr", "memory://urls/reds.dat") == original
    fsspec.filesystem("memory").rm("/urls", recursive=True)


def test_s3_store_and_capture(reds_dat, s3_endpoint, cli_process, tmp_path):
    original = open(reds_dat, "rb").read()
    assert round_trip(reds_dat, "s3://spikes-bucket/reds.zarr", "s3://spikes-bucket/reds.dat") == original

    # The real command line, in its own process, reading a capture from S3 and writing a store there.
    env = {"AWS_ENDPOINT_URL": s3_endpoint}
    result = cli_process("ingest", "s3://spikes-bucket/reds.dat", "s3://spikes-bucket/cli.zarr",
                         "--height", 250, "--width", 400, "--flip", env=env)
    assert result.returncode == 0, result.stderr
    assert '"frames": 301' in cli_process("info", "s3://spikes-bucket/cli.zarr", "--json", env=env).stdout
    missing = cli_process("ingest", "s3://spikes-bucket/none.dat", "s3://spikes-bucket/x.zarr", "--height", 250, "--width", 400, env=env)
    assert missing.returncode == 1 and "none.dat" in missing.stderr


def test_an_output_in_a_missing_bucket_is_named_and_no_bucket_is_made(reds_dat, s3_endpoint, cli, tmp_path):
    """ingest, export and reconstruct said "cannot read The specified bucket does not exist: no such file or
    object" (the output unnamed, and called read); preview made the bucket (s3fs's makedirs) and wrote there."""
    store = "s3://spikes-bucket/missing-bucket-reds.zarr"
    ingest(reds_dat, store, IngestOptions(height=250, width=400, flip=True))
    for args, output in ((["ingest", reds_dat, "s3://no-such-bucket-a/x.zarr", "--height", 250, "--width", 400],
                          "s3://no-such-bucket-a/x.zarr"),
                         (["export", store, "s3://no-such-bucket-b/x.dat"], "s3://no-such-bucket-b/x.dat"),
                         (["preview", store, "s3://no-such-bucket-c/sub/p.png"], "s3://no-such-bucket-c/sub/p.png")):
        result = cli(*args)
        assert result.exit_code == 1 and result.stderr.strip().splitlines() == [
            f"error: cannot write {output}: The specified bucket does not exist"], result.stderr
    s3 = fsspec.filesystem("s3", skip_instance_cache=True)
    assert not any(s3.exists(f"no-such-bucket-{x}") for x in "abc")
