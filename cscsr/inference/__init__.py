"""What runs the network: the pipeline's reconstructor, device-side steps, device memory budgets, ONNX Runtime. Imports: cscsr.weights, cscsr.network, stages."""
