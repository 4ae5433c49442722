"""headforge: animatable 3D head avatars from phone videos or head scans."""

__version__ = "0.1.0"
