"""Output writers of a run and the triggers that say when each acts (in the spirit of HOOMD-blue's writers and
OpenMM's reporters).

A scene (engine.driver.simulate.SceneRun) stops at the steps its step triggers name; at a stop each writer whose trigger
fires acts on the scene's state:

- :mod:`engine.output.writers.records`: the observables of a record step into the result file, and the energy-rise check
  of a dissipative run (trigger: every ``output_every`` steps and the last step);
- :mod:`engine.output.writers.snapshots`: full frames (trigger: the snapshot steps spread over the cooling run);
- :mod:`engine.output.writers.checkpoints`: state and partial file for a resume (trigger: wall-clock interval);
- :mod:`engine.output.writers.progress`: the progress callback (every stop).

:mod:`engine.output.writers.triggers` holds the triggers. The driver (engine.driver.simulate.drive) only advances scenes
to their next stops and calls them there.
"""
