"""The CSCSR network, architecture only, one module per step (docs/network.md), and its configurations: importable without training or inference code. Imports: torch, numpy."""
