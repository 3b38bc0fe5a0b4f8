"""evchain-example: a background-activity (noise) filter, packaged as an evchain plugin."""

__version__ = "0.1.0"
