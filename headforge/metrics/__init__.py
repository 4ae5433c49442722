"""Metrics of the seed papers' tables: image quality, geometry, point-cloud distributions."""
