"""minimdm: auto-regressive motion diffusion, from DDPM to A-MDM, AAMDM and CAMDM."""

__version__ = "0.1.0"
