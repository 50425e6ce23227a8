"""omnirecon: generalizable image-based reconstruction and rendering."""

__version__ = "0.1.0"
