"""Rendering: cameras and a ray-cast reference renderer (the differentiable paths come later)."""
