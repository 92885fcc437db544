"""The set-up of a run: the spec (the public JSON contract), its derived parameters, the precision, the kind of
start and the initial scene — everything fixed before a time loop starts. The map: engine/README.md."""
