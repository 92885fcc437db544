"""The driver: runs a spec (one scene, ``simulate.run``) or several (``ensemble.run_ensemble``) through a
backend, stop to stop, with the GPU's start-up on a thread and the command line's progress. The map:
engine/README.md."""
