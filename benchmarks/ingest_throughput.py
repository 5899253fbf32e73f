"""Ingest throughput of a large raw capture, against ``cp`` of the same file.

What: ``pipeline.jobs.ingest.ingest()`` of a 1000x1000 ``.dat`` capture of 17,000 frames (2.1 GB,
more than any single block or chunk) into a local Zarr spike store, in MB/s of input
(MB = 1e6 bytes). Reference: ``cp`` of the same file on the same disk in the same run,
the fastest anything can move those bytes; ingest reads them, compresses and writes less.
Goal: ingest at least half the speed of cp. Also: the peak RSS of the ingest process (it
streams 64 MiB blocks, so memory must stay far below the file's size) and the bits per
pixel at rest of the resulting store (reference: 1 bit/pixel of the raw packed capture).

The capture is an integrate-and-fire simulation of a smooth, slowly drifting scene
(rates 0.05-0.3 spikes/pixel/frame), not random bits, so the compressor sees realistic
data. It is generated once with numpy in bounded memory and cached under /tmp.

cp and ingest alternate (cp first on even repetitions, ingest first on odd ones); before
each timed step the output is removed and ``sync`` flushes dirty pages, and the share of
the source held in the page cache is recorded (it normally is fully cached: 24 GiB RAM).
Neither step fsyncs its output. Figures are medians over the repetitions.

Run: ``python benchmarks/ingest_throughput.py [--frames N] [--repeats R]``.
"""

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import ROOT, entropy_bits, load_average, markdown_table, median, save_results, write_integrate_and_fire
from pipeline.jobs.info import summarize
from pipeline.jobs.ingest import BLOCK_BYTES
from pipeline.stores.spike_store import CODEC_LEVEL, SpikeMeta, chunk_frames_for

H = W = 1000
FRAME_BYTES = H * W // 8
CACHE = Path("/tmp/cscsr_bench")
BLOCK = 200  # frames generated per block (25 MB packed); the rate map drifts block to block

CHILD = """
import json, resource, sys, time
from pipeline.jobs.ingest import IngestOptions, ingest
rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
start = time.perf_counter()
ingest(sys.argv[1], sys.argv[2], IngestOptions(height=%d, width=%d, overwrite=True), progress=False)
seconds = time.perf_counter() - start
print(json.dumps({"seconds": seconds, "rss_before_kib": rss_before,
                  "rss_peak_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
""" % (H, W)


def rate_map(t: float) -> np.ndarray:
    """Firing rate per pixel in [0.05, 0.3]: a smooth pattern translating 0.01 px/frame."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    x = x - 0.01 * t
    s = 0.5 + 0.3 * np.sin(x / 97) * np.cos(y / 131) + 0.2 * np.sin((x + 0.6 * y) / 53)  # in [0, 1]
    return (0.05 + 0.25 * s).astype(np.float32)


def cached_capture(frames: int) -> Path:
    path = CACHE / f"if_{H}x{W}_{frames}.dat"
    if path.exists() and path.stat().st_size == frames * FRAME_BYTES:
        print(f"using cached capture {path}", file=sys.stderr)
        return path
    CACHE.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    write_integrate_and_fire(path, frames, rate_map, block=BLOCK)
    print(f"generated {path} ({path.stat().st_size / 1e9:.2f} GB) in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return path


def cached_fraction(path: Path) -> float | None:
    """Share of the file resident in the page cache (util-linux ``fincore``), if available."""
    if not shutil.which("fincore"):
        return None
    out = subprocess.run(["fincore", "--bytes", "--noheadings", "--output", "RES", str(path)],
                         capture_output=True, text=True)
    return int(out.stdout.split()[0]) / path.stat().st_size if out.returncode == 0 else None


def prepare(dest: Path, src: Path) -> float | None:
    shutil.rmtree(dest, ignore_errors=True) if dest.is_dir() else dest.unlink(missing_ok=True)
    subprocess.run(["sync"], check=True)
    return cached_fraction(src)


def time_cp(src: Path, dest: Path) -> dict:
    cached = prepare(dest, src)
    start = time.perf_counter()
    subprocess.run(["cp", str(src), str(dest)], check=True)
    return {"seconds": time.perf_counter() - start, "src_cached": cached}


def time_ingest(src: Path, dest: Path) -> dict:
    """ingest() in a fresh interpreter, timed inside it (imports excluded), with its peak RSS."""
    cached = prepare(dest, src)
    out = subprocess.run([sys.executable, "-c", CHILD, str(src), str(dest)], cwd=ROOT,
                         check=True, capture_output=True, text=True)
    return {**json.loads(out.stdout.splitlines()[-1]), "src_cached": cached}


def zstd_alone(src: Path, chunks: int = 16, repeats: int = 3) -> float:
    """MB/s of the store's codec (zstd, CODEC_LEVEL) alone, one thread, on the capture's first chunks."""
    import numcodecs

    frames = chunk_frames_for(SpikeMeta(height=H, width=W), 10**9)
    data = np.fromfile(src, np.uint8, count=chunks * frames * FRAME_BYTES)
    data = data[: data.size // (frames * FRAME_BYTES) * frames * FRAME_BYTES].reshape(-1, frames, H, W // 8)  # whole chunks
    codec, times = numcodecs.Zstd(level=CODEC_LEVEL), []
    for _ in range(repeats):
        start = time.perf_counter()
        for chunk in data:
            codec.encode(chunk)
        times.append(time.perf_counter() - start)
    return data.nbytes / 1e6 / median(times)


def pct(fraction: float | None) -> str:
    return "?" if fraction is None else f"{100 * fraction:.0f}%"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=17000, help="frames of the capture (default 17000, 2.1 GB)")
    parser.add_argument("--repeats", type=int, default=3, help="repetitions of each of cp and ingest (default 3)")
    args = parser.parse_args()
    load_start = load_average()
    src = cached_capture(args.frames)
    size = src.stat().st_size
    work = Path(tempfile.mkdtemp(prefix="ingest-bench-", dir=CACHE))
    runs = []
    try:
        copy, store = work / "copy.dat", work / "store.zarr"
        for rep in range(args.repeats):
            steps = [("cp", lambda: time_cp(src, copy)), ("ingest", lambda: time_ingest(src, store))]
            result = {"rep": rep, "order": [name for name, _ in steps[:: 1 if rep % 2 == 0 else -1]]}
            for name, step in steps[:: 1 if rep % 2 == 0 else -1]:
                result[name] = step()
                print(f"rep {rep} {name}: {size / 1e6 / result[name]['seconds']:.0f} MB/s", file=sys.stderr)
            runs.append(result)
        info = summarize(str(store))
        codec_mbs = zstd_alone(src)
    finally:
        shutil.rmtree(work, ignore_errors=True)

    cp_mbs = median(size / 1e6 / r["cp"]["seconds"] for r in runs)
    ingest_mbs = median(size / 1e6 / r["ingest"]["seconds"] for r in runs)
    peak_rss = max(r["ingest"]["rss_peak_kib"] for r in runs) * 1024
    base_rss = median(r["ingest"]["rss_before_kib"] for r in runs) * 1024
    bpp, rate = info["bits_per_pixel"], info["firing_rate"]
    ratio = ingest_mbs / cp_mbs
    summary = [
        ["throughput, MB/s of input (median)", f"{ingest_mbs:.0f}", f"cp: {cp_mbs:.0f}", f"{ratio:.2f}", ">= 0.5",
         "PASS" if ratio >= 0.5 else "FAIL"],
        ["throughput, MB/s of input (median)", f"{ingest_mbs:.0f}", f"zstd-{CODEC_LEVEL} alone, 1 thread: {codec_mbs:.0f}",
         f"{ingest_mbs / codec_mbs:.2f}", "(context: the codec's own speed)", "-"],
        ["peak RSS of the ingest process, MiB", f"{peak_rss / 2**20:.0f} (imports alone: {base_rss / 2**20:.0f}; growth = {(peak_rss - base_rss) / BLOCK_BYTES:.1f} x the {BLOCK_BYTES // 2**20} MiB read block)",
         f"input file: {size / 2**20:.0f}", f"{peak_rss / size:.3f}", "bounded, far below the file", "PASS" if peak_rss < size / 4 else "FAIL"],
        ["bits/pixel at rest", f"{bpp:.3f}", "raw packed: 1.000", f"{bpp:.3f}", "<= 1.0", "PASS" if bpp <= 1 else "FAIL"],
        ["bits/pixel at rest vs entropy", f"{bpp:.3f}", f"H({rate:.3f}) = {entropy_bits(rate):.3f}",
         f"{bpp / entropy_bits(rate):.3f}", "(i.i.d. bound; I&F data is more predictable)", "-"],
    ]
    per_run = [[r["rep"], " then ".join(r["order"]), f"{r['cp']['seconds']:.2f}", f"{size / 1e6 / r['cp']['seconds']:.0f}",
                f"{r['ingest']['seconds']:.2f}", f"{size / 1e6 / r['ingest']['seconds']:.0f}",
                f"{r['ingest']['rss_peak_kib'] / 1024:.0f}", f"{pct(r['cp']['src_cached'])} / {pct(r['ingest']['src_cached'])}"]
               for r in runs]
    print(f"## Ingest throughput: {args.frames} frames of {H}x{W} ({size / 1e9:.2f} GB .dat), "
          f"integrate-and-fire, mean rate {rate:.3f}\n")
    print(markdown_table(["figure", "ingest", "reference", "ratio", "goal", "result"], summary))
    print()
    print(markdown_table(["rep", "order", "cp s", "cp MB/s", "ingest s", "ingest MB/s", "ingest peak RSS MiB",
                          "source in page cache (cp / ingest)"], per_run))
    print(f"\nMedians of {args.repeats} repetitions each. Load average at start {load_start}, at end {load_average()}; "
          "other work on the machine makes timings noisy. Neither cp nor ingest fsyncs; outputs land in the page cache.")
    path = save_results("ingest_throughput", {
        "frames": args.frames, "height": H, "width": W, "input_bytes": size, "capture": str(src),
        "runs": runs, "cp_mb_s": cp_mbs, "ingest_mb_s": ingest_mbs, "ratio_ingest_cp": ratio,
        "peak_rss_bytes": peak_rss, "rss_after_imports_bytes": base_rss, "peak_rss_over_input": peak_rss / size,
        "ingest_block_bytes": BLOCK_BYTES, "zstd_alone_mb_s": codec_mbs,
        "bits_per_pixel": bpp, "firing_rate": rate, "entropy_bits": entropy_bits(rate), "store_info": info,
        "load_average_at_start": load_start, "goal_ratio": 0.5, "goal_met": ratio >= 0.5,
    })
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
