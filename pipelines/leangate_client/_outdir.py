"""Whose output directory it is: :mod:`leangate_client.reconstruct` replaces ``OUT/images`` and
``OUT/sparse`` only when a run of it made them (a marker file inside); anything else is refused."""

from __future__ import annotations

import os

from .errors import SetupError


#: Written into ``OUT/images`` and ``OUT/sparse`` when this module makes them: a later run
#: replaces (deletes and makes anew) only folders that hold it, never a user's or COLMAP's own.
OUTPUT_MARKER = ".leangate-reconstruct"


#: The folders under ``--out`` that a run replaces.
OUTPUT_SUBDIRS = ("images", "sparse")


def _make_owned_dir(d: str) -> None:
    """Make ``d`` (missing or just removed) with the marker that lets a later run replace it."""
    os.makedirs(d)
    with open(os.path.join(d, OUTPUT_MARKER), "w") as f:
        f.write("made by leangate_client.reconstruct (pipelines/reconstruct.py); a later run "
                "with the same --out deletes and remakes this folder\n")


def check_output_subdir(out_dir: str, sub: str) -> None:
    """Raise SetupError unless ``OUT/sub`` may be replaced: it is missing, an empty folder, or a
    folder this module made (it holds ``OUTPUT_MARKER``). A symbolic link is refused, never
    followed (deleting it would delete what it points to)."""
    p = os.path.join(out_dir, sub)
    if os.path.islink(p):
        raise SetupError(
            f"--out {out_dir}: {p} is a symbolic link (to {os.readlink(p)}); reconstruct.py "
            "does not follow it to replace what it points to; choose another --out or remove it"
        )
    if not os.path.lexists(p):
        return
    if not os.path.isdir(p):
        raise SetupError(
            f"--out {out_dir}: {p} exists and is not a folder; choose another --out or remove it"
        )
    marker = os.path.join(p, OUTPUT_MARKER)
    if os.path.isfile(marker) and not os.path.islink(marker):
        return
    if os.listdir(p):
        raise SetupError(
            f"--out {out_dir}: {p} is not empty and was not made by reconstruct.py (no "
            f"{OUTPUT_MARKER} in it), so it is not replaced; choose another --out or remove it"
        )
