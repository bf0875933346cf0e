"""Measured, not shipped: each module asked one question of the shipped pipeline (`training/`);
the answers are in `training/README.md` ("Experiments") and, at length, in `NOTEBOOK.md` beside
this file. Experiments import the pipeline, never the reverse."""
