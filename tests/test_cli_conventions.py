"""What users of command lines and Dask expect: ``--version``, a dashboard link that serves the dashboard
(bokeh installed) printed on standard error only, and choices shown in ``--help``."""

import re
import urllib.request

from pipeline.compute.cluster import dask_client
from pipeline.compute.executor import dashboard_link
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


def test_flags_are_shown_taking_no_value(cli):
    """Typer showed ``--flip <bool>``, and ``--flip true`` is then refused: a flag takes no value."""
    for command, flag in (("ingest", "--flip"), ("reconstruct", "--resume"), ("watch", "--once"),
                          ("train", "--resume")):
        shown = cli(command, "--help").stdout
        assert flag in shown and "<bool>" not in shown and "<int>" in shown, command


def test_cscsr_alone_prints_its_help(cli_process):
    """Asked for, not a mistake: the help on standard output, status 0 (it was Click's usage error, status 2)."""
    alone = cli_process()
    assert (alone.returncode, alone.stderr) == (0, "") and "Usage: cscsr [OPTIONS] COMMAND" in alone.stdout


def test_a_scheduler_without_a_dashboard_gets_no_link(tmp_path):
    """``dask scheduler --no-dashboard`` still lists a dashboard service, whose page answers 404: its link was
    printed all the same."""
    import json
    import os
    import subprocess
    import sys
    import time

    from distributed import Client

    address_file = tmp_path / "scheduler.json"
    scheduler = subprocess.Popen([os.path.join(os.path.dirname(sys.executable), "dask"), "scheduler", "--host",
                                  "127.0.0.1", "--port", "0", "--scheduler-file", str(address_file), "--no-dashboard"],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 60
        while not address_file.exists() and time.time() < deadline:
            time.sleep(0.2)
        with Client(json.loads(address_file.read_text())["address"], timeout=10) as client:
            assert "dashboard" in client.scheduler_info()["services"]  # listed all the same
            assert dashboard_link(client) is None
    finally:
        scheduler.terminate()
        scheduler.wait(30)


def test_one_task_is_one_task_in_the_result_line(cli, tmp_path):
    """Counts in result lines agree with their nouns: "1 task run", not "1 tasks run" (issue #48)."""
    write_dat(tmp_path / "scene.dat", integrate_and_fire(smooth_rate(16, 16), 41))
    store = tmp_path / "spikes.zarr"
    result = cli("ingest", tmp_path / "scene.dat", store, "--height", 16, "--width", 16, "--workers", 1)
    assert result.exit_code == 0, result.stderr
    assert result.stdout.strip().endswith("(1 task run, 0 already committed)"), result.stdout


def test_the_dashboard_link_goes_to_stderr_never_stdout(cli_process, tmp_path):
    write_dat(tmp_path / "scene.dat", integrate_and_fire(smooth_rate(16, 16), 41))
    store, out = tmp_path / "spikes.zarr", tmp_path / "video.zarr"
    assert cli_process("ingest", tmp_path / "scene.dat", store, "--height", 16, "--width", 16).returncode == 0
    run = cli_process("reconstruct", store, out, "--workers", 1)  # its own local cluster, in a segment process
    assert run.returncode == 0, run.stderr
    assert " ".join(run.stdout.split()) == f"{out}: 1 frame (1 task run, 0 already committed)"  # the result only
    assert re.search(r"^dashboard: http://127\.0\.0\.1:\d+/status$", run.stderr, re.MULTILINE)


def test_help_shows_the_choices_of_method_and_cfa_and_what_export_writes():
    from typer.testing import CliRunner

    from pipeline.cli import app

    def help_of(*command):
        result = CliRunner().invoke(app, [*command, "--help"], env={"COLUMNS": "200"})  # no wrapped choices
        assert result.exit_code == 0
        return " ".join(result.stdout.replace("│", " ").split())

    for command in ("reconstruct", "watch"):
        assert "--method [tfp|tfi|cscsr|cscsr-ensemble]" in help_of(command)
    for command in ("ingest", "simulate", "watch"):
        assert "--cfa [rggb|bggr|grbg|gbrg|mono]" in help_of(command)
    assert "tfp, tfi, cscsr, cscsr-ensemble" in help_of("evaluate")
    export = help_of("export")
    assert ".mp4" in export and "PNG" in export and ".dat" in export


def test_a_value_outside_the_choices_is_one_line(cli, tmp_path):
    write_dat(tmp_path / "scene.dat", integrate_and_fire(smooth_rate(8, 8), 41))
    result = cli("ingest", tmp_path / "scene.dat", tmp_path / "s.zarr", "--height", 8, "--width", 8, "--cfa", "rgbw")
    assert result.exit_code == 1 and result.stderr == ("error: unknown CFA 'rgbw': expected one of rggb, bggr, grbg, "
                                                       "gbrg, mono\n")
    result = cli("reconstruct", tmp_path / "s.zarr", tmp_path / "v.zarr", "--method", "magic")
    assert result.exit_code == 1 and result.stderr.count("\n") == 1 and "magic" in result.stderr
    assert not (tmp_path / "s.zarr").exists() and not (tmp_path / "v.zarr").exists()


def test_help_shows_every_help_text_whole():
    """--help is rich markup: a bare [word] is a tag and prints nothing (``pip install 'cscsr[onnx]'`` came out as
    ``pip install 'cscsr'``). Every command's description and option help is shown whole, brackets escaped as ``\\[``."""
    import typer.main
    from typer.testing import CliRunner

    from pipeline.cli import app

    group = typer.main.get_command(app)
    missing = []
    for name, command in group.commands.items():
        result = CliRunner().invoke(app, [name, "--help"], env={"COLUMNS": "2000"})  # no wrapping
        assert result.exit_code == 0
        shown = " ".join(result.stdout.replace("│", " ").split())
        for text in [command.help or ""] + [p.help for p in command.params if getattr(p, "help", None)]:
            if " ".join(text.replace("\\[", "[").split()) not in shown:
                missing.append(f"{name}: {text}")
    assert not missing, missing
    result = CliRunner().invoke(app, ["reconstruct", "--help"], env={"COLUMNS": "2000"})
    assert "pip install 'cscsr[onnx]'" in " ".join(result.stdout.replace("│", " ").split())
