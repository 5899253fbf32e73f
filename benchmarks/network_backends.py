"""The network on one CPU thread (as each worker runs it) through each backend: PyTorch (the
reference), PyTorch channels-last, ONNX Runtime, and with ``--compile`` torch.compile.

Case: the shipped ``lite`` (or ``--config full``), one window of 41 random spike frames at
``--side`` LR (default 256: the default tile), x4, RGGB. Figures: seconds per window (median of
``--repeats``), speed-up against PyTorch in the same run, one-off start-up (ONNX export and
session, or compilation) and the largest difference from PyTorch's image.

    python benchmarks/network_backends.py [--side 256] [--repeats 3] [--config lite] [--compile]
"""

import argparse
import time

from _common import load_average, markdown_table, random_window, save_results, timed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--config", default="lite", choices=("lite", "full"))
    parser.add_argument("--compile", action="store_true", help="also torch.compile (minutes to compile)")
    args = parser.parse_args()

    import torch

    from cscsr.network.model import use_channels_last
    from cscsr.inference.onnx_runtime import OnnxNetwork
    from cscsr.weights.weights_io import default_weights, load_model

    torch.set_num_threads(1)
    spikes = torch.from_numpy(random_window(args.side))

    def model():
        return load_model(default_weights(args.config))[0]

    def eager(network):
        return lambda: network(spikes, "rggb", False, 4)["image"]

    backends = {"torch (reference)": lambda: (0.0, eager(model())),
                "torch, channels-last": lambda: (0.0, eager(use_channels_last(model())))}
    onnx = OnnxNetwork(model())

    def onnx_backend():
        start = time.perf_counter()
        onnx(spikes, "rggb", False, 4)  # export and session
        return time.perf_counter() - start, lambda: onnx(spikes, "rggb", False, 4)

    backends["ONNX Runtime"] = onnx_backend
    if args.compile:
        def compiled():
            network = torch.compile(model())
            start = time.perf_counter()
            network(spikes, "rggb", False, 4)
            return time.perf_counter() - start, eager(network)

        backends["torch.compile"] = compiled

    rows, results, reference = [], {}, None
    with torch.inference_mode():
        for name, make in backends.items():
            start_up, run = make()
            run()  # warm
            seconds, image = timed(run, args.repeats)
            reference = image if reference is None else reference
            difference = float((image - reference).abs().max())
            results[name] = {"seconds": seconds, "start_up_s": start_up, "max_difference": difference}
            rows.append([name, f"{seconds:.2f}", f"{results['torch (reference)']['seconds'] / seconds:.2f}x",
                         f"{start_up:.0f} s" if start_up else "-", f"{difference:.1e}"])
            print(f"{name}: {seconds:.2f} s", flush=True)
    print(f"\n## {args.config}, one {args.side}x{args.side} LR window (x4), one CPU thread, median of {args.repeats}\n")
    print(markdown_table(["backend", "s per window", "vs torch", "start-up", "max |diff| vs torch"], rows))
    print(f"\nLoad average {load_average()}.")
    save_results("network_backends", {"config": args.config, "side": args.side, "repeats": args.repeats,
                                      "backends": results})


if __name__ == "__main__":
    main()
