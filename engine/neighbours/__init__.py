"""Neighbour search arithmetic shared by the start, the CPU and the CUDA loops: linked cells and the multigrid
cells of size distributions (Skorych & Dosta 2022). The map: engine/README.md."""
