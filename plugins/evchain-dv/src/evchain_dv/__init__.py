"""evchain-dv: AEDAT 4.0 (iniVation DV) files for evchain, via dv-processing."""

__version__ = "0.1.0"
