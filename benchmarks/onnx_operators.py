"""The ONNX export at the GPU run's tile shape, checked for what an ONNX -> TensorRT build needs (#53, item 4).

What: the shipped network exported as ``--backend onnx`` exports it (fp32, opset 18, one graph per kind of
input: ``cscsr.inference.onnx_runtime.export``) for one window of ``--side`` x ``--side`` LR at x4 (the GPU
run's tile: the whole 1000x1000 frame), and ``operator_check``: GridSample at opset >= 16 (the warp), a 5-D
Conv (the BSSR's 3D convolution), DepthToSpace (the pixel shuffle); the operator counts beside.

Tracing runs the network once at that size on the CPU (fp32): ``full`` at 1000x1000 takes about 18 GB there,
so ``--sides`` may give it a smaller side (any side not a multiple of 16 takes the same padding path).

Run: ``python benchmarks/onnx_operators.py [--json] [--configs lite,full] [--sides 1000,504]``.
"""

import argparse
import json
import time

from _common import save_results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", default="lite,full")
    parser.add_argument("--sides", default="1000,504", help="LR side per configuration")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    import torch

    from cscsr.inference.onnx_runtime import export, operator_check
    from cscsr.weights.weights_io import default_weights, load_model

    results = {"runs": []}
    for config, side in zip(args.configs.split(","), (int(s) for s in args.sides.split(","))):
        model, _ = load_model(default_weights(config))
        start = time.perf_counter()
        graph = export(model.eval(), (1, model.config.frames, side, side), "rggb", False, 4)
        check = operator_check(graph)
        results["runs"].append({"config": config, "lr_side": side, "export_seconds": time.perf_counter() - start,
                                "graph_mib": len(graph) / 2**20, **check})
        del graph
        torch.cuda.empty_cache() if torch.cuda.is_available() else None
        print(json.dumps(results["runs"][-1]) if args.json else
              f"{config} at {side}x{side}: {'ok' if check['ok'] else 'PROBLEMS ' + '; '.join(check['problems'])}, "
              f"opset {check['opset']}, GridSample {check['operators'].get('GridSample', 0)}, 5-D Conv "
              f"{check['conv3d']}, DepthToSpace {check['operators'].get('DepthToSpace', 0)}, {check['nodes']} nodes",
              flush=True)
    save_results("onnx_operators", results)


if __name__ == "__main__":
    main()
