"""midas: record and analyse multimodal data in robot-assisted surgery (the MiDAS system)."""

import os

__version__ = "0.1.0"

# OpenMP's threads (torch's CPU kernels) wait for work by spinning unless told otherwise. On a machine
# whose cores are busy with anything else (a recording, a second fold, a CI neighbour) the spinning
# threads take turns with the ones holding work: MS-TCN++ training steps took 3-8x longer (2990 vs
# 378 ms a step with one other busy process on 2 cores; BENCHMARKS.md, "Training on a busy CPU").
# Passive waiting costs ~14 % on an idle machine. Set here, before anything loads torch; a value the
# user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
