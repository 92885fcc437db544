"""Benchmarks and stress tests of demq (run as `demq bench ...` or `python bench/<name>.py`)."""
