"""LeanGate-S training pipeline (run the steps as modules from the repository root:
`python -m training.gen_data`, `python -m training.train`, `python -m training.export`,
`python -m training.calibrate`, `python -m training.evaluate`). Constants live in `training.config`.

Importing the package (or `training.config`, `training.preprocess`) needs only numpy and pillow."""
