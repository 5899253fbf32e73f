"""Helpers shared by the benchmark scripts: paths, medians, markdown tables, JSON results.

Not a benchmark itself (``run_all.py`` skips files whose name starts with ``_``).
"""

import contextlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

median = statistics.median
HIGH_WATER = """
def high_water(pid=None):
    for line in open(f"/proc/{pid or os.getpid()}/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
"""  # source for a benchmark's child interpreter (it imports os): a process's peak resident memory, in bytes


def run_child(code: Path, script: str, *args) -> dict:
    """``script`` in a fresh interpreter in the tree ``code`` (this one, or a :func:`reference_checkout`), given
    ``args``; -> the JSON of its last line of output. A failure stops the benchmark, its error shown."""
    done = subprocess.run([sys.executable, "-c", script, *map(str, args)], cwd=code, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"a run in {code} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def side_by_side(trees: dict[str, Path], repeats: int, work: Path, what: str, script: str, *args) -> dict:
    """``script`` (:func:`run_child`, given ``args`` then a fresh output path under ``work``) in each of ``trees``
    (name -> checkout: "this tree" and "reference"), ``repeats`` times, which runs first alternating, each run's
    figures on standard error; the arrays the outputs share (a reference may lack a newer one) must be equal,
    repetition by repetition (else it stops, naming ``what``) -> name -> its runs' results."""
    import numpy as np
    import zarr

    results = {name: [] for name in trees}
    for repeat in range(repeats):
        outs = {}
        for name, code in (list(trees.items()) if repeat % 2 else list(trees.items())[::-1]):
            outs[name] = work / f"{name.replace(' ', '-')}.zarr"
            shutil.rmtree(outs[name], ignore_errors=True)
            results[name].append(run_child(code, script, *args, outs[name]))
            shown = {k: round(v, 2) if isinstance(v, float) else v for k, v in results[name][-1].items()}
            print(f"{what}, {name}: {shown}", file=sys.stderr, flush=True)
        groups = [zarr.open_group(out, mode="r") for out in outs.values()]
        names = set.intersection(*({name for name, _ in group.arrays()} for group in groups))
        if "spikes" not in names and "video" not in names or not all(
                np.array_equal(group[name][:], groups[0][name][:]) for group in groups for name in names):
            raise SystemExit(f"{what}: the outputs differ from the reference's")
    return results


@contextlib.contextmanager
def reference_checkout(rev: str, prefix: str):
    """(a scratch folder, a checkout of commit ``rev`` in it: ``git worktree``), both removed afterwards."""
    work = Path(tempfile.mkdtemp(prefix=prefix))
    reference = work / "reference"
    subprocess.run(["git", "worktree", "add", "--detach", str(reference), rev], cwd=ROOT, check=True,
                   capture_output=True)
    try:
        yield work, reference
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(reference)], cwd=ROOT, capture_output=True)
        shutil.rmtree(work, ignore_errors=True)


def timed(fn, repeats: int) -> tuple[float, object]:
    """Median seconds of ``repeats`` calls of ``fn``, and its last result."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return median(times), result


def random_window(side: int, frames: int = 41, rate: float = 0.3, seed: int = 0):
    """(1, frames, side, side) float32: a window of random spikes, the network benchmarks' input."""
    import numpy as np

    return (np.random.default_rng(seed).random((1, frames, side, side)) < rate).astype(np.float32)


def entropy_bits(p: float) -> float:
    """Entropy of an i.i.d. Bernoulli(p) pixel, bits: the size bound for memoryless spikes."""
    import math

    return 0.0 if p <= 0 or p >= 1 else -p * math.log2(p) - (1 - p) * math.log2(1 - p)


def load_average() -> str:
    one, five, fifteen = os.getloadavg()
    return f"{one:.2f} / {five:.2f} / {fifteen:.2f} (1 / 5 / 15 min, {os.cpu_count()} CPUs)"


def markdown_table(headers: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def save_results(name: str, data: dict, folder: Path = RESULTS) -> Path:
    """Write ``benchmarks/results/NAME.json`` (or in ``folder``) with the machine's description beside the data."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    machine = {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
               "load_average_at_end": os.getloadavg()}
    path = folder / f"{name}.json"
    path.write_text(json.dumps({"benchmark": name, "machine": machine, **data}, indent=2) + "\n")
    return path


def write_integrate_and_fire(path: Path, frames: int, rate_at, *, seed: int = 0, block: int = 64) -> None:
    """A raw ``.dat`` of integrate-and-fire spikes (subtract reset) in bounded memory.

    ``rate_at(first_frame)`` gives the (H, W) float32 firing rate of a block of frames; each
    pixel adds it every frame and spikes (subtracting 1) at 1, from a seeded random start.
    """
    import numpy as np

    rate = rate_at(0)
    height, width = rate.shape
    acc = np.random.default_rng(seed).random((height, width), dtype=np.float32)
    fire = np.empty((height, width), bool)
    packed = np.empty((block, height, width // 8), np.uint8)
    partial = path.with_suffix(".partial")
    with open(partial, "wb") as out:
        for start in range(0, frames, block):
            rate, n = rate_at(start), min(block, frames - start)
            for i in range(n):
                acc += rate
                np.greater_equal(acc, 1, out=fire)
                np.subtract(acc, fire, out=acc, casting="unsafe")
                packed[i] = np.packbits(fire, axis=-1, bitorder="little")
            packed[:n].tofile(out)
    partial.replace(path)
