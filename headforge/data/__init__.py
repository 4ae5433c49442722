"""Data: video decoding (and, later, preprocessing and datasets)."""
