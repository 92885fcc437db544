"""Result files and exports: the H5MD result file and its writer processes, the XDMF companion, the GSD export,
and the writers of a run with their triggers (``writers/``). The map: engine/README.md."""
