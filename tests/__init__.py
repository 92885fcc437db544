"""Tests of the demq packages (pytest; one folder per package, see tests/README.md)."""
