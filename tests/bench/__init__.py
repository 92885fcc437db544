"""Smoke tests of the bench/ scripts on tiny variants."""
