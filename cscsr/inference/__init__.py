"""What runs the network: the pipeline's reconstructor, device-side steps, device memory budgets, ONNX Runtime. Imports: cscsr.weights, cscsr.network, stages."""

CACHE = "~/.cache/cscsr"  # what the network's runs keep on disk between worker processes and jobs, one folder each
