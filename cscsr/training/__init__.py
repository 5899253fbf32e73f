"""Training: the loop, its data (natural pictures, synthesis of spike windows on the GPU, frame motion). Imports: cscsr.weights, cscsr.network, stages."""
