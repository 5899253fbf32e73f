"""Size at rest of packed spike frames, per codec, against the entropy bound.

What: bits per pixel after compressing the bit-packed frames (np.packbits along x, LSB
first, the store's layout) in whole ~4 MiB chunks of frames (the store's chunking), for
zstd levels 1/3/9/19 and three Blosc variants (numcodecs, one Blosc thread so every codec
runs on one core), plus each codec's encode speed in MB/s of packed input.

Data: firing rates 0.01, 0.1 and 0.3 as i.i.d. Bernoulli frames and as integrate-and-fire
of a static smooth random scene (64 frames of 500x1000 each), and the two bundled real
samples (``cscsr/samples``).

References, measured in the same run: for size, the entropy H(p) of an i.i.d. Bernoulli
pixel at the sample's measured rate p (a true lower bound only for the Bernoulli rows;
integrate-and-fire and real data are more predictable, so they can beat it); for speed,
a plain memory copy of the same chunks. Goals for the chosen codec (zstd at the level
``pipeline/stores/spike_store.py`` uses): <= 1.0 bit/pixel always, and within 15 % of H(p) at
rates >= 0.1. For the real samples the store written by ``ingest()`` is measured too
(``pipeline.jobs.info.summarize``), to confirm the pipeline gets the same size.

Run: ``python benchmarks/size_at_rest.py [--repeats R]``.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numcodecs
import numpy as np
from numcodecs import Blosc, Zstd
from scipy.ndimage import gaussian_filter

from _common import ROOT, entropy_bits, load_average, markdown_table, median, save_results
from pipeline.jobs.info import summarize
from pipeline.jobs.ingest import IngestOptions, ingest
from pipeline.stores.spike_store import CODEC_LEVEL, SpikeMeta, chunk_frames_for

SAMPLES = ROOT / "cscsr" / "samples"
REDS, HELICOPTER = SAMPLES / "synthetic_reds_200_part1_250x400.dat", SAMPLES / "uhsr_u_caltech_helicopter.npz"
CODECS = {
    "zstd-1": Zstd(level=1), "zstd-3": Zstd(level=3), "zstd-9": Zstd(level=9), "zstd-19": Zstd(level=19),
    "blosc-zstd-5-bitshuffle": Blosc("zstd", 5, Blosc.BITSHUFFLE),
    "blosc-zstd-5-noshuffle": Blosc("zstd", 5, Blosc.NOSHUFFLE),
    "blosc-lz4-5-bitshuffle": Blosc("lz4", 5, Blosc.BITSHUFFLE),
}
CHOSEN = f"zstd-{CODEC_LEVEL}"
RATES = (0.01, 0.1, 0.3)
T, H, W = 64, 500, 1000


def pack(bits: np.ndarray) -> np.ndarray:
    return np.packbits(bits, axis=-1, bitorder="little")


def bernoulli(p: float, rng: np.random.Generator) -> np.ndarray:
    return pack(rng.random((T, H, W), dtype=np.float32) < p)


def integrate_and_fire(p: float, rng: np.random.Generator) -> np.ndarray:
    """A static smooth random scene whose rate map has mean p; acc += rate, fire at 1, subtract 1."""
    smooth = gaussian_filter(rng.random((H, W)), sigma=25)
    smooth = (smooth - smooth.min()) / np.ptp(smooth)
    rate = (0.25 + 1.5 * smooth).astype(np.float32)
    rate *= p / rate.mean()
    acc, frames = rng.random((H, W), dtype=np.float32), np.empty((T, H, W), bool)
    for t in range(T):
        acc += rate
        frames[t] = acc >= 1
        acc -= frames[t]
    return pack(frames)


def samples(rng: np.random.Generator) -> dict[str, tuple[np.ndarray, int, float | None]]:
    """name -> (packed frames (T, H, ceil(W/8)), image width W, nominal rate or None if real)."""
    out = {}
    for p in RATES:
        out[f"bernoulli p={p}"] = bernoulli(p, rng), W, p
        out[f"integrate-and-fire p={p}"] = integrate_and_fire(p, rng), W, p
    out["real: synthetic_reds 250x400 (.dat)"] = np.fromfile(REDS, np.uint8).reshape(-1, 250, 400 // 8), 400, None
    out["real: uhsr helicopter 250x250 (.npz)"] = pack(np.load(HELICOPTER)["spk"].astype(bool)), 250, None
    return out


def chunks_of(packed: np.ndarray, width: int) -> list[np.ndarray]:
    """Whole-frame chunks of about 4 MiB, exactly as the spike store cuts them."""
    n = chunk_frames_for(SpikeMeta(height=packed.shape[1], width=width), packed.shape[0])
    return [np.ascontiguousarray(packed[i : i + n]) for i in range(0, packed.shape[0], n)]


def measure(encode, chunks: list[np.ndarray], repeats: int) -> tuple[int, float]:
    """(total encoded bytes, median seconds to encode every chunk)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        encoded = [encode(chunk) for chunk in chunks]
        times.append(time.perf_counter() - start)
    return sum(len(e) if isinstance(e, bytes) else e.nbytes for e in encoded), median(times)


def store_bpp(name: str, tmp: Path) -> float | None:
    """Bits/pixel of a real spike store written by ingest() from the sample file."""
    if not name.startswith("real"):
        return None
    src, options = (REDS, IngestOptions(height=250, width=400)) if ".dat" in name else (HELICOPTER, IngestOptions())
    dest = tmp / f"{src.stem}.zarr"
    ingest(str(src), str(dest), options, progress=False)
    return summarize(str(dest))["bits_per_pixel"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed repetitions per codec and sample (default 3)")
    args = parser.parse_args()
    numcodecs.blosc.set_nthreads(1)
    load_start = load_average()
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, (packed, width, nominal) in samples(np.random.default_rng(0)).items():
            pixels = packed.shape[0] * packed.shape[1] * width
            p = int(np.bitwise_count(packed).sum(dtype=np.int64)) / pixels
            h = entropy_bits(p)
            chunks = chunks_of(packed, width)
            _, copy_s = measure(np.copy, chunks, args.repeats)
            codecs = {}
            for codec_name, codec in CODECS.items():
                nbytes, seconds = measure(codec.encode, chunks, args.repeats)
                codecs[codec_name] = {"bytes": nbytes, "bpp": 8 * nbytes / pixels, "bpp_over_entropy": 8 * nbytes / pixels / h,
                                      "encode_mb_s": packed.nbytes / 1e6 / seconds, "encode_over_memcpy": copy_s / seconds}
            chosen = codecs[CHOSEN]["bpp"]
            in_store = store_bpp(name, Path(tmp))
            goal_1bit = chosen <= 1.0
            goal_entropy = chosen / h <= 1.15 if (nominal or p) >= 0.1 else None  # nominal rate where there is one
            results.append({"sample": name, "shape": list(packed.shape[:2]) + [width], "rate": p, "nominal_rate": nominal, "entropy_bits": h,
                            "memcpy_mb_s": packed.nbytes / 1e6 / copy_s, "codecs": codecs, "store_bpp": in_store,
                            "goal_le_1bit": goal_1bit, "goal_within_15pct_entropy": goal_entropy})
    codec_names = list(CODECS)
    mark = {n: f"**{n}** (chosen)" if n == CHOSEN else n for n in codec_names}
    size_rows = [[r["sample"], f"{r['rate']:.4f}", f"{r['entropy_bits']:.4f}"]
                 + [f"{r['codecs'][n]['bpp']:.4f} ({r['codecs'][n]['bpp_over_entropy']:.2f})" for n in codec_names]
                 + ["-" if r["store_bpp"] is None else f"{r['store_bpp']:.4f} ({r['store_bpp'] / r['codecs'][CHOSEN]['bpp']:.3f})",
                    "PASS" if r["goal_le_1bit"] else "FAIL",
                    {None: "n/a (p < 0.1)", True: "PASS", False: "FAIL"}[r["goal_within_15pct_entropy"]]]
                 for r in results]
    speed_rows = [[r["sample"], f"{r['memcpy_mb_s']:.0f}"]
                  + [f"{r['codecs'][n]['encode_mb_s']:.0f} ({r['codecs'][n]['encode_over_memcpy']:.3f})" for n in codec_names]
                  for r in results]
    print("## Size at rest: bits/pixel (ratio to the entropy bound H(p))\n")
    print(markdown_table(["sample", "rate p", "H(p) bits"] + [mark[n] for n in codec_names]
                         + [f"ingest() store bpp (ratio to {CHOSEN})", f"{CHOSEN}: <= 1 bit/pixel", f"{CHOSEN}: <= 1.15 H(p) at p >= 0.1"],
                         size_rows))
    print(f"\n## Encode speed: MB/s of packed input, median of {args.repeats} (ratio to a memory copy)\n")
    print(markdown_table(["sample", "memcpy MB/s"] + [mark[n] for n in codec_names], speed_rows))
    print(f"\nChunks of ~4 MiB of whole frames as in the store; Blosc limited to 1 thread. H(p) is the i.i.d. bound: "
          f"integrate-and-fire and real rows may go below it. Load average at start {load_start}, at end {load_average()}; "
          "other work on the machine makes the speeds noisy (sizes are exact).")
    path = save_results("size_at_rest", {"chosen_codec": CHOSEN, "repeats": args.repeats, "samples": results,
                                         "load_average_at_start": load_start})
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
