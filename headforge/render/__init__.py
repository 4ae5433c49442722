"""Rendering: cameras, a differentiable mesh rasterizer and point splatter with fast kernels
and pure-PyTorch references, SH shading, mattes, a ray-cast reference renderer, and the PNG/MP4
writers."""
