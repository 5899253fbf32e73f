"""Measures and references: PSNR and correlation, the quality ceilings' references, pictures side by side. Imports: any room of stages."""
