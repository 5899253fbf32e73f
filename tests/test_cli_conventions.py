"""What users of command lines and Dask expect: ``--version``, a dashboard link that serves the dashboard
(bokeh installed) printed on standard error only, and choices shown in ``--help``."""

import re
import urllib.request

from pipeline.cluster import dashboard_link, dask_client
from tests.conftest import integrate_and_fire, smooth_rate, write_dat


def test_version(cli, cli_process):
    from cscsr import __version__

    assert re.fullmatch(r"\d+\.\d+\.\d+", __version__)
    result = cli("--version")
    assert (result.exit_code, result.stdout) == (0, f"cscsr {__version__}\n")
    process = cli_process("--version")
    assert (process.returncode, process.stdout, process.stderr) == (0, f"cscsr {__version__}\n", "")


def test_a_local_clusters_dashboard_link_serves_the_dashboard():
    with dask_client(workers=1) as client:
        link = dashboard_link(client)
        assert link and link.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(link, timeout=30) as response:
            status, page = response.status, response.read().decode()
    assert status == 200 and "<html" in page.lower() and "bokeh" in page.lower()
    assert "needs bokeh" not in page


def test_the_dashboard_link_goes_to_stderr_never_stdout(cli_process, tmp_path):
    write_dat(tmp_path / "scene.dat", integrate_and_fire(smooth_rate(16, 16), 41))
    store, out = tmp_path / "spikes.zarr", tmp_path / "video.zarr"
    assert cli_process("ingest", tmp_path / "scene.dat", store, "--height", 16, "--width", 16).returncode == 0
    run = cli_process("reconstruct", store, out, "--workers", 1)  # its own local cluster, in a segment process
    assert run.returncode == 0, run.stderr
    assert " ".join(run.stdout.split()) == f"{out}: 1 frames (1 tasks run, 0 already committed)"  # the result only
    assert re.search(r"^dashboard: http://127\.0\.0\.1:\d+/status$", run.stderr, re.MULTILINE)
