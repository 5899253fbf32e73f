"""The pages say what the code does, and the package is what its metadata says: README's documented defaults
are the command line's, the docs name modules that exist and no folder outside the repository, and the wheel
carries its licence and weights, built without a warning."""

import pathlib
import re
import subprocess
import sys
import tomllib
import zipfile

import pytest
import yaml

ROOT = pathlib.Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text()
PAGES = {path.relative_to(ROOT).as_posix(): path.read_text()
         for path in [ROOT / "README.md", ROOT / "benchmarks" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]}
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_readme_shows_the_command_lines_defaults():
    """``[--option value]`` in README's command table is the option's default (placeholders such as ``N`` or
    ``FILE`` and choice lists aside); an option whose default is worked out says it in its help, ``(default: value``."""
    import typer.main

    from pipeline.cli import app

    commands = typer.main.get_command(app).commands
    checked, wrong = 0, []
    for row in (line for line in README.splitlines() if line.startswith("| `cscsr ")):
        for usage in re.findall(r"`cscsr ([^`]+)`", row.split(" | ")[0]):
            name = usage.split()[0]
            if name not in commands:
                continue  # `cscsr -q|--quiet COMMAND`
            for option, value in re.findall(r"\[(--[a-z-]+) ([^\s\[\]|\\]+)(?=\]| \\\|)", usage):
                if re.fullmatch(r"[A-Z]+", value):
                    continue
                param = next(p for p in commands[name].params if option in p.opts)
                default = param.default
                same = (f"(default: {value}" in (param.help or "") if default is None
                        else float(value) == default if isinstance(default, float) else str(default) == value)
                checked += 1
                if not same:
                    wrong.append(f"cscsr {name} {option}: README {value}, --help {default!r}")
    assert not wrong, wrong
    assert checked > 10


def test_the_docs_point_at_nothing_outside_the_repository():
    """A user has the repository, not the developers' ``../shared`` folder (data and specs not distributed)."""
    found = [f"{name}:{number}" for name, text in PAGES.items()
             for number, line in enumerate(text.splitlines(), 1) if "../shared" in line or "/work/" in line]
    assert not found, found


def test_the_network_page_names_modules_that_exist():
    named = set(re.findall(r"`([a-z_]+\.py)`", PAGES["docs/network.md"]))
    assert "motion_estimation.py" in named
    assert not {name for name in named if not any((ROOT / "cscsr").rglob(name))}


def test_formats_page_puts_the_head_columns_where_the_code_drops_them():
    from stages.capture.dat import DatLayout

    assert DatLayout(4, 8, head_columns=8).head_at == "end" and DatLayout(4, 8, head_columns=8).first_column == 0
    assert "`--head-columns N` drops N header columns at the end of each row" in PAGES["docs/formats.md"]


def test_readme_and_reliability_page_give_the_same_suite_time():
    times = re.findall(r"about (\d+) minutes on 2 cores", README)
    assert times and re.search(rf"which takes ~{times[0]} minutes on 2 cores", PAGES["docs/reliability.md"])


def test_readme_shows_a_cpu_only_install_and_a_gpu_install():
    assert "pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu && pip install ." in README
    assert re.search(r"^pip install \.\s+# with an NVIDIA GPU", README, re.MULTILINE)
    assert "torch==2.13.0" in (ROOT / "constraints.txt").read_text().splitlines()  # the version the CPU line pins


def test_licence_and_citation():
    assert PYPROJECT["project"]["license"] == "MIT" and PYPROJECT["project"]["license-files"] == ["LICENSE"]
    licence = (ROOT / "LICENSE").read_text()
    assert licence.startswith("MIT License\n") and "Copyright (c) 2026 the cscsr authors" in licence
    # setuptools takes an SPDX string for `license` (and reads `license-files`) from version 77
    assert any(re.fullmatch(r"setuptools>=(\d+)", r) and int(r.split(">=")[1]) >= 77
               for r in PYPROJECT["build-system"]["requires"])
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["license"] == "MIT"
    assert citation["version"] == PYPROJECT["project"]["version"]
    paper = citation["references"][0]
    assert paper["title"] == "Super-Resolution Reconstruction from Bayer-Pattern Spike Streams" and paper["year"] == 2024
    assert [a["family-names"] for a in paper["authors"]] == ["Dong", "Xiong", "Zhang", "Yu", "Fan", "Zhu", "Huang"]


def test_package_data_globs_match_files_of_listed_packages():
    import setuptools as setuptools_package

    setuptools = PYPROJECT["tool"]["setuptools"]
    packages = setuptools_package.find_packages(str(ROOT), include=setuptools["packages"]["find"]["include"])
    for package, globs in setuptools["package-data"].items():
        assert package in packages, package
        for glob in globs:
            assert list((ROOT / package.replace(".", "/")).glob(glob)), f"{package}: {glob} matches no file"


@pytest.mark.timeout(300)
def test_the_wheel_builds_without_warnings_and_carries_weights_samples_and_licence(tmp_path):
    """What ``pip wheel .`` does for a user (an isolated build with setuptools from the registry), on a copy of
    what the wheel is built from, so that the build leaves nothing in the working tree."""
    source = tmp_path / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        (source / name).write_bytes((ROOT / name).read_bytes())
    for package in ("cscsr", "stages", "pipeline"):
        subprocess.run(["cp", "-r", ROOT / package, source / package], check=True)
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--disable-pip-version-check", "--no-deps", "-w",
                            tmp_path / "wheel", source], capture_output=True, text=True, timeout=280)
    assert build.returncode == 0, build.stderr[-2000:]
    log = build.stdout + build.stderr
    assert not re.findall(r"\w+Warning\b", log), log[-3000:]  # setuptools' BuildBackendWarning and the like
    (wheel,) = (tmp_path / "wheel").glob("cscsr-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"cscsr/weights/cscsr-lite.safetensors", "cscsr/weights/cscsr-full.safetensors",
            "cscsr/samples/README.md"} <= names
    modules = {str(path.relative_to(source)) for package in ("cscsr", "stages", "pipeline")
               for path in (source / package).rglob("*.py")}
    assert modules - names == set()  # every module: pipeline/cli, the command's own, was missing
    assert any(name.endswith(".dist-info/licenses/LICENSE") for name in names)


def documented_outputs(code: str) -> list[str]:
    """The comment line right below each ``print(...)`` of an example: what it prints (``...``: what varies)."""
    lines = code.splitlines()
    return [after.strip()[2:] for line, after in zip(lines, lines[1:])
            if line.lstrip().startswith("print(") and after.strip().startswith("# ")]


def test_the_lazy_graphs_example_prints_what_the_page_says(tmp_path):
    """docs/python.md's lazy example, run as a script in an empty folder: every line it prints as its comment says."""
    code = re.search(r"## Lazy graphs.*?```python\n(.*?)```", PAGES["docs/python.md"], re.S)[1]
    (tmp_path / "example.py").write_text(code)
    done = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    printed, expected = done.stdout.splitlines(), documented_outputs(code)
    assert len(expected) == 9 and len(printed) == len(expected), done.stdout
    for line, documented in zip(printed, expected):
        assert re.fullmatch(".*".join(map(re.escape, documented.split("..."))), line), (line, documented)
    assert (tmp_path / "hr.zarr" / "zarr.json").exists() and (tmp_path / "mine.zarr" / "zarr.json").exists()


def _anchors(text: str) -> set[str]:
    """The anchors a Markdown page's headings get (GitHub's rule: lower case, punctuation dropped, spaces to '-',
    a repeated heading numbered)."""
    found, seen, fenced = set(), {}, False
    for line in text.splitlines():
        fenced = fenced != line.startswith("```")
        heading = re.match(r"(#+)\s+(.*)", line) if not fenced else None
        if heading:
            title = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.group(2)).replace("`", "")
            slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
            found.add(f"{slug}-{seen[slug]}" if slug in seen else slug)
            seen[slug] = seen.get(slug, 0) + 1
    return found


def test_every_link_between_the_pages_reaches_a_file_and_its_heading():
    """A relative link names a file of the repository and, after '#', a heading of that page (a renamed heading
    left training.md pointing at gpu.md's old anchor)."""
    broken = []
    for name, text in PAGES.items():
        for number, line in enumerate(text.splitlines(), 1):
            for link in re.findall(r"\]\(([^)\s]+)\)", line):
                if re.match(r"[a-z]+:", link):
                    continue
                path, _, anchor = link.partition("#")
                target = (ROOT / name).parent / path if path else ROOT / name
                if not target.exists():
                    broken.append(f"{name}:{number}: {link} (no such file)")
                elif anchor and target.suffix == ".md" and anchor not in _anchors(target.read_text()):
                    broken.append(f"{name}:{number}: {link} (no such heading)")
    assert not broken, broken


def test_every_python_name_the_pages_give_exists():
    """``pipeline.jobs.simulate_plan.TRUTH_SCALES`` and the like, in backticks, import (a constant moved between
    modules left layout.md naming one that did not); logger names aside."""
    import importlib

    missing, checked = [], 0
    for name, text in PAGES.items():
        for dotted in re.findall(r"(?<!logger )`((?:stages|pipeline|cscsr)(?:\.[A-Za-z_]\w*)+)`", text):
            parts = dotted.split(".")
            for cut in range(len(parts), 0, -1):
                try:
                    found = importlib.import_module(".".join(parts[:cut]))
                    break
                except ImportError:
                    continue
            try:
                for part in parts[cut:]:
                    found = getattr(found, part)
                checked += 1
            except AttributeError:
                missing.append(f"{name}: {dotted}")
    assert not missing, missing
    assert checked > 40
