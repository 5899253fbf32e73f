"""The code's layout holds (docs/layout.md, the one map): packages and their rooms import downwards only, no
circle, no crowded room, no long module; and each fact has one home ("One home for each fact"). Read from the
source, so an import that runs back up, or a copy that creeps back in, fails here."""

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGES = ("pipeline", "cscsr", "stages")  # from the top floor down
# Each package's rooms, from the top floor down ("": the modules at the package's own top level)
FLOORS = {
    "pipeline": ["cli", "", "inbox", "lazy", "jobs", "stores", "compute"],
    "cscsr": ["", "training", "inference", "weights", "network", "samples"],
    "stages": ["measures", "simulation", "reconstruction", "capture", ""],
}
FACADES = {("cscsr", ""): "pipeline"}  # cscsr's lazy Python API loads pipeline.api on first use (importlib)
MOST_MODULES, MOST_LINES = 12, 500
LONGER = {"pipeline/jobs/ingest.py"}  # docs/layout.md says why


def _modules(package: str) -> list[pathlib.Path]:
    return sorted((ROOT / package).rglob("*.py"))


def _room(path: pathlib.Path) -> tuple[str, str]:
    """(package, room) of a module: its first folder under the package ("" at the package's top)."""
    parts = path.relative_to(ROOT).parts
    return parts[0], parts[1] if len(parts) > 2 else ""


def _imported(path: pathlib.Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _module_of(name: str) -> pathlib.Path | None:
    """The project's module (or package) a dotted name names, if any."""
    parts = name.split(".")
    while parts:
        candidate = ROOT.joinpath(*parts)
        for path in (candidate.with_suffix(".py"), candidate / "__init__.py"):
            if parts[0] in PACKAGES and path.is_file():
                return path
        parts.pop()
    return None


def _floor(package: str, room: str) -> tuple[int, int]:
    return PACKAGES.index(package), FLOORS[package].index(room)


def _arrows() -> dict[pathlib.Path, set[pathlib.Path]]:
    return {path: {m for name in _imported(path) if (m := _module_of(name)) and m != path}
            for package in PACKAGES for path in _modules(package)}


def test_every_room_is_on_the_map():
    for package in PACKAGES:
        rooms = {_room(path)[1] for path in _modules(package)}
        assert rooms <= set(FLOORS[package]), f"{package}: rooms not in FLOORS (and docs/layout.md): {rooms - set(FLOORS[package])}"


def test_imports_run_downwards_only():
    """A module imports its own room, rooms below it in its package, and packages below its own; never up."""
    up = {}
    for path, targets in _arrows().items():
        here = _floor(*_room(path))
        for target in targets:
            there = _room(target)
            if _floor(*there) < here and FACADES.get(_room(path)) != there[0]:
                up.setdefault(str(path.relative_to(ROOT)), []).append(str(target.relative_to(ROOT)))
    assert not up, f"imports that run back up: {up}"


def test_no_circle_of_imports():
    arrows = _arrows()
    index, low, stack, on_stack, circles = {}, {}, [], set(), []

    def visit(node):  # Tarjan: strongly connected components of more than one module
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for target in arrows.get(node, ()):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in on_stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                circles.append(sorted(str(m.relative_to(ROOT)) for m in component))

    for node in arrows:
        if node not in index:
            visit(node)
    assert not circles, f"circles of imports: {circles}"


def test_no_crowded_room_and_no_long_module():
    crowded = {}
    for package in PACKAGES:
        for folder in {path.parent for path in _modules(package)}:
            modules = [p for p in folder.glob("*.py") if p.name != "__init__.py"]
            if len(modules) > MOST_MODULES:
                crowded[str(folder.relative_to(ROOT))] = len(modules)
    assert not crowded, f"rooms of more than {MOST_MODULES} modules: {crowded}"
    files = [*(p for package in PACKAGES for p in _modules(package)), *(ROOT / "benchmarks").glob("*.py")]
    long = {str(p.relative_to(ROOT)): n for p in files if (n := len(p.read_text().splitlines())) > MOST_LINES
            and str(p.relative_to(ROOT)) not in LONGER}
    assert not long, f"modules over {MOST_LINES} lines that docs/layout.md does not explain: {long}"


def test_each_room_says_what_lives_there():
    for package in PACKAGES:
        for init in (ROOT / package).glob("*/__init__.py"):
            doc = ast.get_docstring(ast.parse(init.read_text())) or ""
            assert "Imports" in doc or init.parent.name in ("lazy", "samples"), f"{init}: say what lives here and what it may import"


def _definitions(pattern: str) -> list[str]:
    found = []
    for package in PACKAGES:
        for path in _modules(package):
            for number, line in enumerate(path.read_text().splitlines(), 1):
                if re.match(pattern, line):
                    found.append(f"{path.relative_to(ROOT).as_posix()}:{number}")
    return found


@pytest.mark.parametrize("fact, pattern, home", [
    ("the 41-frame window", r"^WINDOW\s*=", ["stages/reconstruction/methods.py"]),
    ("the reset modes", r"^RESETS\s*=", ["stages/capture/resets.py"]),
    ("the network's precisions", r"^PRECISIONS\s*=", ["cscsr/network/config.py"]),
    ("a float image to 8 bits", r"^def to_uint8\(", ["stages/simulation/intensities.py"]),
    ("an error as one line", r"^def describe\(", ["stages/errors.py"]),
    ("the window centres", r"^def output_centres\(", ["stages/reconstruction/methods.py"]),
    ("prefetching", r"^def (prefetched|made_ahead)\(", ["stages/prefetch.py", "stages/prefetch.py"]),
])
def test_each_fact_is_defined_once(fact, pattern, home):
    assert [place.split(":")[0] for place in _definitions(pattern)] == home, f"{fact}: {_definitions(pattern)}"


def test_errors_are_made_one_line_by_describe_alone():
    copies = [place for place in _definitions(r".*[\"'] [\"']\.join\(str\(.*\)\.split\(\)\)")
              if place.split(":")[0] != "stages/errors.py"]
    assert not copies, f"one-line error text made outside stages.errors.describe: {copies}"


def test_zarr_groups_are_opened_by_the_store_modules_alone():
    owners = {"pipeline/stores/storage.py", "pipeline/stores/spike_store.py", "pipeline/stores/video_store.py"}
    opened = [place for place in _definitions(r".*zarr\.open(_group|_array)?\(") if place.split(":")[0] not in owners]
    assert not opened, f"a store opened outside its format's module: {opened}"


def test_the_old_module_paths_import_the_modules_now_in_rooms():
    """``pipeline.spike_store`` and every other module path of the flat house (docs/python.md named some) still
    import, as the very module of its room, with a DeprecationWarning naming the new path."""
    import subprocess
    import sys

    code = ("import importlib, warnings\n"
            "warnings.simplefilter('error')\n"
            "for old, new in [('pipeline.spike_store', 'pipeline.stores.spike_store'),\n"
            "                 ('pipeline.reconstruct', 'pipeline.jobs.reconstruct'), ('stages.tfp', 'stages.reconstruction.tfp'),\n"
            "                 ('cscsr.reconstructor', 'cscsr.inference.reconstructor')]:\n"
            "    try:\n"
            "        importlib.import_module(old)\n"
            "    except DeprecationWarning as warning:\n"
            "        assert new in str(warning), warning\n"
            "    else:\n"
            "        raise AssertionError(f'{old}: no warning')\n"
            "    with warnings.catch_warnings():\n"
            "        warnings.simplefilter('ignore')\n"
            "        moved = importlib.import_module(old)\n"
            "    assert moved is importlib.import_module(new) and moved.__spec__.name == new, old\n"
            "warnings.simplefilter('ignore')\n"
            "from pipeline.images import write_image  # as docs/python.md's example once wrote it\n")
    done = subprocess.run([sys.executable, "-W", "ignore::DeprecationWarning", "-c", code.replace(
        "warnings.simplefilter('error')\n", "warnings.simplefilter('error', DeprecationWarning)\n")],
        capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
