#!/usr/bin/env python3
"""pipelines/reconstruct.py — the frames leangate keeps, into COLMAP (pycolmap) incremental SfM.

A thin wrapper around `leangate_client.reconstruct` (the package beside this file), runnable from
the checkout. Needs pycolmap and the system's PyGObject: `bash scripts/setup.sh` makes
`.venv-sfm` (a venv with --system-site-packages and pycolmap), so:

    .venv-sfm/bin/python pipelines/reconstruct.py clip.mp4 --out out/rec --ply out/rec/points.ply -v
    .venv-sfm/bin/python pipelines/reconstruct.py ../shared/data/7scenes_redkitchen_dev --max-gap 6
    .venv-sfm/bin/python pipelines/reconstruct.py SEQ --frames 0,10,20,30   # no gate: these frames
    .venv-sfm/bin/python pipelines/reconstruct.py SEQ --every 10            # dense reference

The plugin is found through GST_PLUGIN_PATH (or --plugin-path); when neither has it, this
wrapper also tries the repository's target/release and target/debug.
"""

import os
import sys

# pycolmap before the GStreamer bindings: importing pycolmap after gi's Gst/GstVideo crashes
# (SIGSEGV/abort while unwinding a C++ exception at import) in about half of the runs.
try:
    import pycolmap  # noqa: F401
except ImportError:
    pass  # reported with the fix by leangate_client.reconstruct.import_pycolmap

from leangate_client.reconstruct import main as _main  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PLUGIN_FALLBACKS = [os.path.join(REPO, "target", p) for p in ("release", "debug")]


def main(argv=None) -> int:
    return _main(argv, prog="reconstruct", plugin_fallbacks=PLUGIN_FALLBACKS)


if __name__ == "__main__":
    sys.exit(main())
