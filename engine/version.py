"""The engine's version string (written into every result file); a leaf module, so any engine module may import it."""

__version__ = "0.1.0"
