"""Weights: the shipped .safetensors files beside the code that reads and writes them, portable checkpoints, a model's description. Imports: cscsr.network."""
