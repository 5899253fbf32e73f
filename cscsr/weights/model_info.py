"""What ``cscsr model-info`` prints: a configuration's settings and its parameters per step."""

from cscsr.network.config import CSCSRConfig, named
from cscsr.network.integration import NETWORK_SCALES


def _count(module) -> int:
    return sum(p.numel() for p in module.parameters()) if module is not None else 0


def model_info(config: str | None = None, weights: str | None = None) -> dict[str, str]:
    """Rows for a table: from a named configuration, or from a weights file's metadata."""
    from cscsr.network.model import CSCSR

    metadata = {}
    if weights is not None:
        from cscsr.weights.weights_io import load_model

        model, metadata = load_model(weights)
    else:
        model = CSCSR(named(config or "lite"))
    cfg: CSCSRConfig = model.config
    counts = model.parameter_counts()
    rows = {
        "configuration": cfg.name,
        "parameters (network, as the paper counts)": f"{counts['network']:,} ({counts['network'] / 1e6:.2f} M)",
        "  BSSR (mono)" if cfg.mono else "  BSSR (R, G, B)": f"{_count(model.bssr):,}",
        "  temporal-pixel features": f"{_count(model.temporal):,}",
        "  integration and upsampling": f"{_count(model.integration):,}",
        "parameters (spike-flow network, apart)": f"{counts['flow']:,} ({counts['flow'] / 1e6:.2f} M)",
        "frames N, window w, stride s -> N'": f"{cfg.frames}, {cfg.length}, {cfg.stride} -> {cfg.time_points}",
        "colours": "mono: one branch, every pixel; grey output as three equal channels" if cfg.mono
                   else "Bayer: R, G, B branches",
        "features C (per colour), F (trunk), ResBlocks": f"{cfg.colour_features}, {cfg.features}, {cfg.blocks}",
        "motion estimation": f"{cfg.motion}, flow guidance {'on' if cfg.flow_guidance else 'off'}",
        "scales": ", ".join(map(str, NETWORK_SCALES)),
    }
    rows.update({f"weights: {k}": v for k, v in metadata.items() if k not in ("config", "format")})
    return rows
