"""Every constant of the training pipeline in one place: model input, normalisation, name, the split
of the real sequence tum_fr1_rpy, seeds, and default paths (no machine-specific ones).

Paths:
  REPO         the repository (parent of this package)
  SHARED       real data, read in place: $LEANGATE_SHARED_DATA, else <repo>/../shared/data
  DATA_ROOT    everything generated (sequences, caches, checkpoints, reports):
               $LEANGATE_TRAIN_DATA, else <repo>/out/train-data (git-ignored)
  LEANGATE     the CLI: $LEANGATE, else target/release/leangate, else target/debug/leangate,
               else `leangate` on PATH
"""
import os
import shutil

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SHARED = os.environ.get("LEANGATE_SHARED_DATA") or os.path.normpath(os.path.join(REPO, "..", "shared", "data"))
DATA_ROOT = os.environ.get("LEANGATE_TRAIN_DATA") or os.path.join(REPO, "out", "train-data")
MODELS_DIR = os.path.join(REPO, "models")


def leangate_bin():
    env = os.environ.get("LEANGATE")
    if env:
        return env
    for p in (os.path.join(REPO, "target", "release", "leangate"), os.path.join(REPO, "target", "debug", "leangate")):
        if os.path.exists(p):
            return p
    return shutil.which("leangate") or os.path.join(REPO, "target", "release", "leangate")


LEANGATE = leangate_bin()

# ---------------------------------------------------------------------------------------- model
NAME = "leangate-s"
IN_W, IN_H = 160, 120  # model input, short-side-crop
RESIZE = "short-side-crop"
MEAN = (0.485, 0.456, 0.406)  # ImageNet, applied by the element after scaling to [0,1]
STD = (0.229, 0.224, 0.225)
DEFAULT_THRESHOLD = 0.5  # the paper's tau_keep, in the teacher's units (the export is calibrated)

# ------------------------------------------------------------------------- real data: the split
# tum_fr1_rpy (718 frames, 30 Hz): three contiguous parts with 15-frame guard gaps, so no labelled
# pair straddles two parts. Inclusive frame ranges (indices into the associated frame list).
TUM_SEQ = "tum_fr1_rpy"
TUM_SPLIT = {
    "train": (0, 399),   # real training pairs (teacher labels)
    "cal": (415, 559),   # calibration of the exported utility; model selection
    "test": (575, 717),  # never used for fitting or selection: reported only
}

# The second real sequence, tum_fr1_desk (572 frames, fast handheld sweeps over office desks): never
# trained on by the student. `fit` is where cross-sequence fusions and calibrations may be fitted;
# `test` is reported only. A 14-frame guard gap, as above.
DESK_SEQ = "tum_fr1_desk"
DESK_SPLIT = {
    "fit": (0, 285),
    "test": (300, 571),
}
# Every real labelled sequence and its documented split (training.fuse reports each part).
REAL_SPLITS = {TUM_SEQ: TUM_SPLIT, DESK_SEQ: DESK_SPLIT}
# Two more real sequences, split the same way for fine-tuning the student's head
# (`training.experiments.finetune`): tum_fr1_xyz (595 frames, the same Kinect and office, slow translation) and
# 7scenes_redkitchen_long (940 frames, another Kinect and room); both are rebuilt by the importers
# (training/README.md). `fit` may be trained on; `test` is reported only (15-frame guard gaps).
XYZ_SEQ = "tum_fr1_xyz"
XYZ_SPLIT = {"fit": (0, 289), "test": (305, 594)}
SEVEN_SEQ = "7scenes_redkitchen_long"
SEVEN_SPLIT = {"fit": (0, 459), "test": (475, 939)}
# Every documented split (training.tum.make_part writes any part of them).
ALL_SPLITS = {**REAL_SPLITS, XYZ_SEQ: XYZ_SPLIT, SEVEN_SEQ: SEVEN_SPLIT}
# What `training.experiments.finetune` trains the head on: each sequence's fitting part (tum_fr1_rpy's train part,
# which the student was trained on already; not its cal part, where the fusion is fitted).
FINETUNE_PARTS = {TUM_SEQ: "train", DESK_SEQ: "fit", XYZ_SEQ: "fit", SEVEN_SEQ: "fit"}
# Where the element's fusion of the student with the geometric prior is fitted (training.fuse):
# tum_fr1_rpy's cal part (not its train part: the student was trained there, so its utility is
# in-sample) and tum_fr1_desk's fit part. The test parts are reported only.
FUSION_FIT_PARTS = {TUM_SEQ: ["cal"], DESK_SEQ: ["fit"]}

# -------------------------------------------------------------------------- synthetic data
MOTIONS = ["static", "pan", "shaky", "walk", "rotate", "bursts", "mixed", "mixed", "mixed", "walk", "shaky"]
# photos whose names start with these are held out of training (validation homographies, eval textures)
HELDOUT_PREFIXES = ("paragliding", "apple")
TRAIN_SEED0, VAL_SEED0, EVAL_SEED0 = 1000, 5000, 9001
REPLAY_SEED0 = 2000  # gen_data --steps replay: real trajectories + sensor realism
ROLL_SEED0 = 2100  # gen_data --steps roll: the train trajectory with an added roll
