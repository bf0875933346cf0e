"""LeanGate-S training pipeline (run the steps as modules from the repository root:
`python -m training.gen_data`, `python -m training.train`, `python -m training.export`,
`python -m training.calibrate`, `python -m training.evaluate`). Constants live in `training.config`.

Importing the package (or `training.config`, `training.preprocess`) needs only numpy and pillow.

ONNX Runtime's telemetry is switched off here, before any module of the package imports
onnxruntime: Microsoft's wheels otherwise write a device id and queued usage events under
~/.cache/Microsoft when the module loads (a user's own ORT_DISABLE_TELEMETRY is kept)."""

import os

os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")
