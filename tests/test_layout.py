"""The code's layout holds: layers import downwards only, and each fact has one home
(docs/layout.md, "One home for each fact"). Read from the source, so a copy that creeps back in fails here."""

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGES = ("stages", "cscsr", "pipeline")


def _modules(package: str) -> list[pathlib.Path]:
    return sorted((ROOT / package).glob("*.py"))


def _imported(path: pathlib.Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


@pytest.mark.parametrize("package, below", [("stages", ()), ("cscsr", ("stages",))])
def test_layers_import_downwards_only(package, below):
    """stages import no other layer; cscsr only stages (its lazy Python API aside); pipeline anything."""
    others = set(PACKAGES) - {package} - set(below)
    offending = {}
    for path in _modules(package):
        if path.name in ("__init__.py", "__main__.py"):
            continue  # by design: cscsr's lazy Python API (pipeline.api on first use) and `python -m cscsr` (the CLI)
        bad = sorted(name for name in _imported(path) if name.split(".")[0] in others)
        if bad:
            offending[path.name] = bad
    assert not offending, f"{package} imports from a layer above it: {offending}"


def _definitions(pattern: str) -> list[str]:
    found = []
    for package in PACKAGES:
        for path in _modules(package):
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if re.match(pattern, line):
                    found.append(f"{package}/{path.name}:{number}")
    return found


@pytest.mark.parametrize("fact, pattern, home", [
    ("the 41-frame window", r"^WINDOW\s*=", ["stages/methods.py"]),
    ("the reset modes", r"^RESETS\s*=", ["stages/sensor.py"]),
    ("the network's precisions", r"^PRECISIONS\s*=", ["cscsr/config.py"]),
    ("a float image to 8 bits", r"^def to_uint8\(", ["stages/intensities.py"]),
    ("an error as one line", r"^def describe\(", ["stages/errors.py"]),
    ("the window centres", r"^def output_centres\(", ["stages/methods.py"]),
    ("prefetching", r"^def (prefetched|made_ahead)\(", ["stages/prefetch.py", "stages/prefetch.py"]),
])
def test_each_fact_is_defined_once(fact, pattern, home):
    assert [place.split(":")[0] for place in _definitions(pattern)] == home, f"{fact}: {_definitions(pattern)}"


def test_errors_are_made_one_line_by_describe_alone():
    copies = [place for place in _definitions(r".*[\"'] [\"']\.join\(str\(.*\)\.split\(\)\)")
              if place.split(":")[0] != "stages/errors.py"]
    assert not copies, f"one-line error text made outside stages.errors.describe: {copies}"


def test_zarr_groups_are_opened_by_the_store_modules_alone():
    owners = {"pipeline/storage.py", "pipeline/spike_store.py", "pipeline/video_store.py"}
    opened = [place for place in _definitions(r".*zarr\.open(_group|_array)?\(") if place.split(":")[0] not in owners]
    assert not opened, f"a store opened outside its format's module: {opened}"
