"""``cscsr watch``: how recordings and their sidecars are named and told apart: a sidecar's name in any case, one
still being written, the same bytes under two names, one INBOX spelt three ways, names no log line may split."""

import json
import os

import zarr

from pipeline.inbox.ledger import Ledger
from pipeline.inbox.watch import WatchOptions, discover, watch_once
from tests.test_watch import drop, settled
from tests.test_watch_log import tiny_capture

SIDECAR = {"height": 16, "width": 16, "cfa": "rggb"}
QUICK = WatchOptions(tile=16, every=5, settle=0)


def shown(outbox) -> dict:
    """name -> (state, final, error) of each recording as ``cscsr status`` shows it."""
    return {row.name: (row.state, row.final, row.error) for row in Ledger(outbox).recordings()}


def test_a_sidecar_in_upper_case_is_read_and_one_still_being_written_waits_to_settle(tmp_path, client):
    """``cam.NPY`` beside ``cam.JSON``: the capture was taken, its sidecar never read (a mono capture reconstructed
    as RGGB, no word said); two sidecars of one capture are refused as such. A sidecar still being written
    (half its JSON, just modified) was refused at once as not JSON, whatever --settle: now the recording waits
    to settle, sidecar included, and is taken once its sidecar is whole."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    (inbox / "cam.NPY").write_bytes(tiny_capture())
    (inbox / "cam.JSON").write_text(json.dumps({"cfa": "mono"}))
    drop(inbox, "twin.npy", tiny_capture(1), SIDECAR)
    (inbox / "twin.JSON").write_text(json.dumps(SIDECAR))
    drop(inbox, "late.npy", tiny_capture(2))
    settled(inbox)
    (inbox / "late.json").write_text('{"height": 16, "wi')  # being written now

    counts = watch_once(str(inbox), str(outbox), WatchOptions(tile=16, every=5, settle=10), client)
    assert counts == {"processed": 1, "waiting": 1, "skipped": 0, "refused": 1}
    assert shown(outbox) == {"cam": ("done", 0, None),
                             "twin": ("failed", 1, "2 sidecars for twin.npy: twin.JSON, twin.json: keep one")}
    assert zarr.open_group(str(outbox / "spikes" / "cam.zarr"), mode="r").attrs["cfa"] == "mono"

    (inbox / "late.json").write_text(json.dumps(SIDECAR))  # whole now
    settled(inbox)
    counts = watch_once(str(inbox), str(outbox), WatchOptions(tile=16, every=5, settle=10), client)
    assert counts == {"processed": 1, "waiting": 0, "skipped": 2, "refused": 0}
    assert shown(outbox)["late"] == ("done", 0, None)
    assert not [row for row in Ledger(outbox).rows() if row.name == "late" and row.state == "failed"]


def test_the_same_bytes_under_another_name_have_a_status_line_of_their_own(tmp_path, client, cli, caplog):
    """Byte-identical recordings under two names: the second got no output and no status line (one DEBUG line
    only), and a third, refused for its sidecar, kept showing that stale refusal once its sidecar was fixed. Now
    each is a ``duplicate`` line naming the recording done, said once at INFO."""
    import logging

    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    for name in ("a", "b", "c"):
        drop(inbox, f"{name}.npy", tiny_capture(), SIDECAR)
    (inbox / "c.json").write_text(json.dumps({**SIDECAR, "colour": True}))
    settled(inbox)
    with caplog.at_level(logging.DEBUG, logger="cscsr.watch"):
        first = watch_once(str(inbox), str(outbox), QUICK, client)
        (inbox / "c.json").write_text(json.dumps(SIDECAR))  # fixed
        settled(inbox)
        second = watch_once(str(inbox), str(outbox), QUICK, client)
    assert first == {"processed": 1, "waiting": 0, "skipped": 1, "refused": 1}
    assert second == {"processed": 0, "waiting": 0, "skipped": 3, "refused": 0}
    assert {name: state[:2] for name, state in shown(outbox).items()} == {
        "a": ("done", 0), "b": ("duplicate", 0), "c": ("duplicate", 0)}
    said = [record.getMessage() for record in caplog.records if record.levelno == logging.INFO and " same bytes" in
            record.getMessage()]
    assert said == [f"{name}: same bytes and parameters as a ({inbox / 'a.npy'}): not done again, its outputs are "
                    f"a's" for name in ("b", "c")]  # once each
    assert sorted(path for path in os.listdir(outbox) if not path.startswith(".")) == [
        "a.mp4", "a.zarr", "ledger.sqlite", "spikes"]
    table = cli("status", outbox).stdout
    assert "duplicate" in table and "same bytes as a:" in next(line for line in table.splitlines() if "│ b " in line)
    assert json.loads(cli("status", outbox, "--json").stdout)[1]["output"] == "a"


def test_one_inbox_spelt_several_ways_is_one_inbox_in_the_ledger(tmp_path, client, cli, monkeypatch):
    """``in``, ``./in/``, a link to it and its absolute path: each spelling keyed the ledger anew, so a refusal was
    logged again at every spelling (and a --once pass failed for it), and status showed a line per spelling."""
    inbox, outbox = tmp_path / "in", tmp_path / "out"
    inbox.mkdir()
    (tmp_path / "link").symlink_to(inbox)
    drop(inbox, "a.npy", tiny_capture(), SIDECAR)
    drop(inbox, "notes.txt", b"hello")
    settled(inbox)
    monkeypatch.chdir(tmp_path)

    first = watch_once("in", str(outbox), QUICK, client)
    assert first == {"processed": 1, "waiting": 0, "skipped": 0, "refused": 1}
    for spelling in ("./in/", str(tmp_path / "link"), f"file://{inbox}"):
        assert watch_once(spelling, str(outbox), QUICK, client) == {"processed": 0, "waiting": 0, "skipped": 2,
                                                                    "refused": 0}, spelling
    again = cli("watch", "./in", "out", "--once", "--workers", 1, "--settle", 0, "--tile", 16, "--every", 5)
    assert again.exit_code == 0, again.stderr  # the refusal was said before: nothing new
    assert f"INFO cscsr.watch: pass over {inbox}: 0 processed, 0 still settling, 2 already handled, 0 refused" \
        in again.stderr
    rows = json.loads(cli("status", outbox, "--json").stdout)
    assert [(row["name"], row["source"], row["state"]) for row in rows] == [
        ("a", str(inbox / "a.npy"), "done"), ("notes", str(inbox / "notes.txt"), "failed")]


def test_a_name_too_long_is_refused_for_its_length(tmp_path):
    """A name of 140 letters was refused as ``letters, digits, '.', '_' and '-' only``, which it is: the limit it
    broke is its length, 128 characters, which is now what the refusal says; 128 are taken."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "n" * 140 + ".npy", tiny_capture(), SIDECAR)
    settled(inbox)
    counts = watch_once(str(inbox), str(outbox), WatchOptions(settle=10), client=None)
    assert counts == {"processed": 0, "waiting": 0, "skipped": 0, "refused": 1}
    reason = f"name {'n' * 140!r} is 140 characters long: at most 128 (rename the recording, or give its sidecar a " \
             f"shorter 'name')"
    assert shown(outbox) == {"n" * 140: ("failed", 1, reason)}
    (inbox / ("n" * 140 + ".npy")).rename(inbox / ("m" * 128 + ".npy"))
    assert [(found.name, found.problem) for found in discover(str(inbox))] == [("m" * 128, None)]


def test_bytes_refused_for_their_name_are_done_under_another_and_bad_bytes_stay_refused(tmp_path, client):
    """``b.npy`` whose sidecar names it ``a``, a name ``a.npy`` holds, is refused for its name; the same bytes as
    ``c.npy`` were then a ``duplicate`` of that refusal, never done: the name's refusal no longer holds the bytes.
    Bytes refused as bad input (a truncated capture) under another name are refused too, in that refusal's words,
    not shown as a duplicate of outputs that do not exist."""
    inbox, outbox = tmp_path / "inbox", tmp_path / "outbox"
    inbox.mkdir()
    drop(inbox, "a.npy", tiny_capture(0), {"cfa": "rggb"})
    drop(inbox, "b.npy", tiny_capture(1), {"cfa": "rggb", "name": "a"})
    drop(inbox, "t.npy", tiny_capture(2)[:-100], {"cfa": "rggb"})
    settled(inbox)
    by_file = lambda: {os.path.basename(row.source): (row.state, row.final, row.error)  # noqa: E731
                       for row in Ledger(outbox).recordings()}
    watch_once(str(inbox), str(outbox), QUICK, client)
    before = by_file()
    assert before["a.npy"] == ("done", 0, None) and before["t.npy"][:2] == ("failed", 1)
    assert before["b.npy"] == ("failed", 1, f"output name 'a' already belongs to {inbox / 'a.npy'} (other bytes or "
                                            f"parameters): rename the recording or give its sidecar a 'name'")

    drop(inbox, "c.npy", tiny_capture(1), {"cfa": "rggb"})
    drop(inbox, "u.npy", tiny_capture(2)[:-100], {"cfa": "rggb"})
    settled(inbox)
    counts = watch_once(str(inbox), str(outbox), QUICK, client)
    assert counts["processed"] == 1 and counts["refused"] == 1
    after = by_file()
    assert after["c.npy"] == ("done", 0, None) and (outbox / "c.zarr").exists()
    assert after["u.npy"] == ("failed", 1, f"the same bytes and parameters as t, refused: {before['t.npy'][2]}")
