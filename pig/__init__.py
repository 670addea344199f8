"""PiG-Avatar: hierarchical neural-field-guided Gaussian avatars from multi-view video."""

__version__ = "0.1.0"
