"""Reduced physics validation runs (homogeneous cooling against theory)."""
