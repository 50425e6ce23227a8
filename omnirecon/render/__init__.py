"""Rendering operators that take callbacks and never own a network."""
