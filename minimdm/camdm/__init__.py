"""CAMDM (Chen et al. 2024), chapter 9."""
