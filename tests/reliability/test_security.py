"""Security properties that a code change could quietly break: on the source itself, and on real inboxes,
ledgers and clusters."""

import ast
import json
import logging
import os
import time
from pathlib import Path

import pytest
import yaml

from pipeline.inbox.ledger import _SCHEMA
from stages.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("cscsr", "stages", "pipeline")


def sources():
    for package in PACKAGES:
        yield from sorted((ROOT / package).rglob("*.py"))


def calls(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            yield node


def name_of(call: ast.Call) -> str:
    f = call.func
    parts = []
    while isinstance(f, ast.Attribute):
        parts.append(f.attr)
        f = f.value
    if isinstance(f, ast.Name):
        parts.append(f.id)
    return ".".join(reversed(parts))


def test_weights_never_go_through_pickle():
    for path in sources():
        tree = ast.parse(path.read_text())
        for call in calls(tree):
            assert name_of(call) not in ("torch.load", "pickle.load", "pickle.loads", "np.load", "numpy.load"), \
                f"{path.relative_to(ROOT)}:{call.lineno}: {name_of(call)} can run pickled code"
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] + [getattr(node, "module", None) or ""]
                assert "pickle" not in names, f"{path.relative_to(ROOT)}:{node.lineno} imports pickle"


def test_no_shell_command_is_built_from_strings():
    for path in sources():
        for call in calls(ast.parse(path.read_text())):
            name = name_of(call)
            assert name not in ("os.system", "os.popen", "subprocess.getoutput"), f"{path.relative_to(ROOT)}:{call.lineno}"
            shell = [k for k in call.keywords if k.arg == "shell"]
            assert not shell or (isinstance(shell[0].value, ast.Constant) and shell[0].value.value is False), \
                f"{path.relative_to(ROOT)}:{call.lineno}: shell=True"


def test_the_scheduler_is_published_on_loopback_only():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    for name, service in compose["services"].items():
        for port in service.get("ports", []):
            text = port if isinstance(port, str) else f"{port.get('host_ip', '')}:{port.get('published')}"
            assert text.startswith("127.0.0.1:"), f"{name} publishes {port} beyond this machine"
    assert "TLS" in (ROOT / "docker-compose.yml").read_text() and "tls" in (ROOT / "docs" / "cluster.md").read_text()


def test_inbox_links_that_leave_the_inbox_are_refused_and_nothing_is_read_through_them(tmp_path, caplog):
    """A symbolic link in INBOX (the recording, a file inside a Zarr store, or a sidecar) whose real path
    is elsewhere: recorded as failed with its reason; nothing copied, ingested or exported."""
    from pipeline.inbox.ledger import Ledger
    from pipeline.inbox.watch import WatchOptions, watch_once

    inbox, outbox, elsewhere = tmp_path / "inbox", tmp_path / "outbox", tmp_path / "private"
    inbox.mkdir()
    elsewhere.mkdir()
    (elsewhere / "secret.dat").write_bytes(bytes(range(256)) * 64)
    (elsewhere / "store.zarr").mkdir()
    (elsewhere / "store.zarr" / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group"}')
    (elsewhere / "sidecar.json").write_text('{"height": 8, "width": 16}')
    (inbox / "linked.dat").symlink_to(elsewhere / "secret.dat")  # the recording itself
    (inbox / "linked_store.zarr").symlink_to(elsewhere / "store.zarr")  # a whole store
    (inbox / "mixed.zarr").mkdir()  # a store of its own whose metadata is a link out
    (inbox / "mixed.zarr" / "zarr.json").symlink_to(elsewhere / "store.zarr" / "zarr.json")
    (inbox / "own.dat").write_bytes(bytes(128))  # a real file, with a sidecar that is a link out
    (inbox / "own.json").symlink_to(elsewhere / "sidecar.json")
    (inbox / "dangling.dat").symlink_to(tmp_path / "gone" / "x.dat")
    (inbox / "inside.dat").symlink_to(inbox / "own.dat")  # a link that stays inside is not an escape...
    (inbox / "inside.json").write_text('{"cfa": "mono"}')  # (its CFA stated: none is guessed)
    past = time.time() - 60
    os.utime(inbox / "own.dat", (past, past))

    with caplog.at_level(logging.INFO, logger="cscsr.watch"):
        counts = watch_once(str(inbox), str(outbox), WatchOptions(settle=0), client=None)
    failures = [record.getMessage() for record in caplog.records if record.levelno >= logging.ERROR]
    rows = {row.name: row for row in Ledger(outbox).rows()}
    escaped = {"linked", "linked_store", "mixed", "own", "dangling"}
    for name in escaped:
        row = rows[name]
        assert (row.state, row.final) == ("failed", 1), row
        assert "leads outside the inbox" in row.error and "\n" not in row.error, row.error
    assert "linked.dat -> " + str(elsewhere / "secret.dat") in rows["linked"].error
    assert "mixed.zarr/zarr.json -> " in rows["mixed"].error and "own.json -> " in rows["own"].error
    assert "give both --height and --width" in rows["inside"].error  # ...it is taken, and judged on its bytes
    assert counts["refused"] == len(escaped) + 1 and len(failures) == len(escaped) + 1  # and inside's, one each
    assert sorted(os.listdir(outbox)) == ["ledger.sqlite"]  # nothing ingested, reconstructed or exported
    assert (elsewhere / "secret.dat").read_bytes() == bytes(range(256)) * 64


def test_a_local_cluster_listens_on_loopback_only_dashboard_included():
    """Every listening socket of a local cluster (scheduler, its dashboard, the workers and their
    nannies) is bound to 127.0.0.1, and the dashboard link says where it really is."""
    import psutil

    from pipeline.compute.cluster import dask_client
    from pipeline.compute.executor import dashboard_link

    def listening(process):
        return {(c.laddr.ip, c.laddr.port) for c in process.net_connections(kind="inet") if c.status == psutil.CONN_LISTEN}

    me = psutil.Process()
    before = listening(me)
    with dask_client(workers=1) as client:
        ours = listening(me) - before  # the scheduler and its dashboard run in this process
        for child in me.children(recursive=True):
            ours |= listening(child)
        dashboard_port = client.scheduler_info()["services"]["dashboard"]
        link = dashboard_link(client)
    assert ours and {ip for ip, _ in ours} == {"127.0.0.1"}, ours
    assert ("127.0.0.1", dashboard_port) in ours
    assert link.startswith(f"http://127.0.0.1:{dashboard_port}/")


def snapshot(folder) -> dict:
    return {p.relative_to(folder): p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


def test_a_ledger_is_opened_only_if_it_is_ours_and_status_never_writes(tmp_path, cli):
    """``status`` or ``watch`` on an OUTBOX holding someone else's ``ledger.sqlite`` (another program's
    database, a file that is not a database, a folder): one line naming the file, not a byte changed,
    nothing added beside it. Our own ledger, with or without the marker, is read by ``status`` untouched."""
    import sqlite3

    from pipeline.inbox.ledger import APPLICATION_ID, Ledger
    from tests.test_bad_input import assert_refused

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    with sqlite3.connect(foreign / "ledger.sqlite") as db:
        db.execute("CREATE TABLE photos (id INTEGER PRIMARY KEY, path TEXT)")
        db.execute("INSERT INTO photos (path) VALUES ('holiday.jpg')")
    garbage, folder = tmp_path / "garbage", tmp_path / "folder"
    garbage.mkdir()
    (garbage / "ledger.sqlite").write_bytes(b"my notes, not a database\n" * 10)
    (folder / "ledger.sqlite").mkdir(parents=True)
    cases = [(foreign, "is an SQLite database but not a cscsr ledger (tables: photos)"),
             (garbage, "is not an SQLite database (file is not a database)"),
             (folder, "is a folder, not an SQLite database")]
    (tmp_path / "inbox").mkdir()  # a watcher refuses a missing INBOX first
    for outbox, fragment in cases:
        before = snapshot(outbox)
        assert_refused(cli("status", outbox), f"{outbox / 'ledger.sqlite'}", fragment)
        assert_refused(cli("watch", tmp_path / "inbox", outbox, "--once"), fragment)  # before a lock or a cluster
        with pytest.raises(InputError, match="not"):
            Ledger(outbox)
        assert snapshot(outbox) == before and sorted(p.name for p in outbox.iterdir()) == ["ledger.sqlite"]

    ours = tmp_path / "ours"
    Ledger(ours).record_refusal("k", "bad", "inbox/bad.dat", "sidecar bad.json is not JSON")
    old = tmp_path / "old"  # a ledger from before the marker: our table, application_id 0
    old.mkdir()
    with sqlite3.connect(old / "ledger.sqlite") as db:
        db.execute(_SCHEMA)
    for outbox in (ours, old):
        before, stamp = snapshot(outbox), os.stat(outbox / "ledger.sqlite").st_mtime_ns
        result = cli("status", outbox, "--json")
        assert result.exit_code == 0, result.stderr
        assert snapshot(outbox) == before and os.stat(outbox / "ledger.sqlite").st_mtime_ns == stamp
    assert json.loads(cli("status", ours, "--json").stdout)[0]["error"] == "sidecar bad.json is not JSON"
    with sqlite3.connect(ours / "ledger.sqlite") as db:
        assert db.execute("PRAGMA application_id").fetchone()[0] == APPLICATION_ID
    assert_refused(cli("status", tmp_path / "nowhere"), "has no ledger (ledger.sqlite)")
