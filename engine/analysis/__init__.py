"""Analysis of results and the theory they are compared with: Haff's law and Luding's ODE, hydrodynamic modes,
the shear instability, velocity correlations, ensemble statistics. The map: engine/README.md."""
