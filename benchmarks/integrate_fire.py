"""Integrate-and-fire throughput of the sensor model, against a plain numpy loop over frames.

What: ``stages.simulation.sensor.fire()`` (numba, parallel over rows, bytes packed in the kernel) on
precomputed increments of a 1000x1000 sensor, in Gpixel-frames/s (1e9 pixel x frames per
second), for both resets. Reference: in the same run, the obvious numpy loop over frames
(``acc += q; s = acc >= thr; acc -= s * thr`` or ``np.where(s, 0, acc)``; ``np.packbits``),
whose output must equal fire()'s bit for bit (checked, so the comparison is honest).
Goal: fire() at least 10x the loop. Context rows, no goal: fire() with per-pixel
thresholds (realistic noise), ``increments()`` without and with realistic noise (the stage
before fire, to show the next bottleneck), and numpy's normal generator alone (what the
realistic noise has to draw per frame).

The scene is a smooth pattern drifting 0.5 px/frame (intensities 0.1-0.9, brightness 0.6).
fire() is called once untimed first (numba compiles or loads its cache); fire() and the
loop alternate order between repetitions; figures are medians, and the ratio is the median
of the ratios within each repetition (robust to load that drifts between repetitions).
Every call allocates its output, as the pipeline's calls do, so page faults on fresh memory
are included.

Run: ``python benchmarks/integrate_fire.py [--frames N] [--repeats R]``.
"""

import argparse
import sys
import time

import numba
import numpy as np

from _common import load_average, markdown_table, median, save_results
from stages.simulation.sensor import UNITS, SensorModel, fire, increments, initial_state, pixel_thresholds

H = W = 1000
GOAL = 10.0


def scene(frames: int) -> np.ndarray:
    """(frames, H, W) float32 intensities in [0.1, 0.9]: a smooth pattern drifting 0.5 px/frame."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    out = np.empty((frames, H, W), np.float32)
    for t in range(frames):
        xt = x - 0.5 * t
        out[t] = 0.5 + 0.25 * np.sin(xt / 37) * np.cos(y / 53) + 0.15 * np.sin((xt + 0.6 * y) / 23)
    return out


def numpy_loop(q: np.ndarray, state: np.ndarray, reset: str) -> tuple[np.ndarray, np.ndarray]:
    """The reference: (n, H, W) int32 increments -> (n, H, W/8) packed spikes and the final state."""
    acc = state.copy()
    packed = np.empty((q.shape[0], H, W // 8), np.uint8)
    for t in range(q.shape[0]):
        acc += q[t]
        s = acc >= UNITS
        if reset == "subtract":
            acc -= s * UNITS
        else:
            acc = np.where(s, 0, acc)
        packed[t] = np.packbits(s, axis=-1, bitorder="little")
    return packed, acc


def timed(call) -> tuple[float, object]:
    start = time.perf_counter()
    result = call()
    return time.perf_counter() - start, result


def throughput(pixel_frames: int, seconds: list[float]) -> float:
    return pixel_frames / median(seconds) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=64, help="frames per call (default 64)")
    parser.add_argument("--repeats", type=int, default=7, help="timed repetitions of each step (default 7)")
    args = parser.parse_args()
    load_start = load_average()
    n, pixel_frames = args.frames, args.frames * H * W
    intensities = scene(n)
    clean, noisy = SensorModel(), SensorModel(noise="realistic")
    q = increments(clean, intensities, 0)
    state = initial_state(clean, H, W)
    thresholds = pixel_thresholds(noisy, H, W)
    print(f"mean firing rate {q.mean() / UNITS:.3f}; numba {numba.__version__}, "
          f"{numba.get_num_threads()} threads", file=sys.stderr)

    times = {name: [] for name in ("fire zero", "fire subtract", "numpy zero", "numpy subtract",
                                   "fire per-pixel thresholds", "increments none", "increments realistic",
                                   "normals alone")}
    identical = {}
    for reset in ("zero", "subtract"):
        fire(q, state, reset=reset)  # compile (or load numba's cache) and touch the memory
        for rep in range(args.repeats):
            steps = [("fire", lambda: fire(q, state, reset=reset)), ("numpy", lambda: numpy_loop(q, state, reset))]
            for name, step in steps[:: 1 if rep % 2 == 0 else -1]:
                seconds, result = timed(step)
                times[f"{name} {reset}"].append(seconds)
                if name == "fire":
                    fired = result
                else:
                    packed, final = result
            identical[reset] = identical.get(reset, True) and bool(
                np.array_equal(fired.packed, packed) and np.array_equal(fired.state, final))
            print(f"{reset} rep {rep}: fire {pixel_frames / times[f'fire {reset}'][-1] / 1e9:.2f}, numpy "
                  f"{pixel_frames / times[f'numpy {reset}'][-1] / 1e9:.3f} Gpix/s", file=sys.stderr)

    fire(q, state, reset="subtract", thresholds=thresholds)
    increments(noisy, intensities[:1], 0)
    normals = np.empty((H, W), np.float32)
    for _ in range(args.repeats):
        times["fire per-pixel thresholds"].append(timed(lambda: fire(q, state, reset="subtract",
                                                                     thresholds=thresholds))[0])
        times["increments none"].append(timed(lambda: increments(clean, intensities, 0))[0])
        times["increments realistic"].append(timed(lambda: increments(noisy, intensities, 0))[0])
        times["normals alone"].append(timed(lambda: [
            np.random.default_rng([0, 2, t]).standard_normal(dtype=np.float32, out=normals) for t in range(n)])[0])

    speed = {name: throughput(pixel_frames, seconds) for name, seconds in times.items()}
    ratios = {reset: median(loop / fast for loop, fast in zip(times[f"numpy {reset}"], times[f"fire {reset}"]))
              for reset in ("zero", "subtract")}
    rows = []
    for reset in ("zero", "subtract"):
        fast, loop, ratio = speed[f"fire {reset}"], speed[f"numpy {reset}"], ratios[reset]
        rows.append([f"fire(), reset {reset}", f"{fast:.2f}", f"numpy loop: {loop:.3f}", f"{ratio:.1f}",
                     f">= {GOAL:.0f}", "PASS" if ratio >= GOAL and identical[reset] else "FAIL"])
    for name, label in (("fire per-pixel thresholds", "fire(), subtract, per-pixel thresholds"),
                        ("increments none", "increments(), noise none"),
                        ("increments realistic", "increments(), noise realistic"),
                        ("normals alone", "default_rng(...).standard_normal alone, float32")):
        rows.append([label, f"{speed[name]:.3f}", "-", "-", "(context)", "-"])
    print(f"## Integrate-and-fire throughput: {n} frames of {H}x{W}, Gpixel-frames/s\n")
    print(markdown_table(["figure", "Gpix-frames/s", "reference", "ratio", "goal", "result"], rows))
    print(f"\nfire() output equals the numpy loop's bit for bit: zero {identical['zero']}, subtract "
          f"{identical['subtract']}. Medians of {args.repeats} runs; numba {numba.get_num_threads()} threads "
          f"({numba.threading_layer()}). Load average at start {load_start}, at end {load_average()}; "
          "other work on the machine makes timings noisy.")
    path = save_results("integrate_fire", {
        "frames": n, "height": H, "width": W, "seconds": times, "gpixel_frames_per_s": speed,
        "ratio_fire_numpy": ratios,
        "bit_identical": identical, "numba_threads": numba.get_num_threads(),
        "threading_layer": numba.threading_layer(), "load_average_at_start": load_start, "goal_ratio": GOAL,
        "goal_met": all(ratios[r] >= GOAL and identical[r] for r in ("zero", "subtract")),
    })
    print(f"\n(results: {path})")


if __name__ == "__main__":
    main()
