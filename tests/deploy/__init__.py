"""Tests of the files in deploy/, with real processes where a machine without Docker, Slurm or systemd allows."""
