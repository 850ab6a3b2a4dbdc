"""Zero-correction baseline for experiments/results/graph_guess.md: MAE N/E/D of the guesses themselves
(WLS, and the no-prior graph solution) on the validation split of the SF-2 leave-one-out training data.

    OMP_NUM_THREADS=1 PYTHONPATH=. python experiments/graph_guess_baseline.py

Data: ``$GNSSFUSE_SHARED_DATA`` (default ``<repo>/../shared/data``). The ``sim-bias`` source now takes
``--sim-traces`` like ``sim`` (30 traces each; the results file was made with 20 bias traces, so its
validation split differs slightly).
"""
import os
from pathlib import Path

import numpy as np
from fusion.eval.metrics import ned_errors
from learned.data import split_blocks
from learned.train_command import load_training_data
SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
D = SHARED / "gsdc2021" / "train"
s, _ = load_training_data(["sim", "sim-bias", f"{D}/2020-05-14-US-MTV-1/Pixel4", f"{D}/2020-06-05-US-MTV-1/Pixel4"],
                          sim_traces=30, sim_epochs=200, seed=0, elev_mask_deg=10.0, with_graph=True)
_, va = split_blocks(s, 0.1, np.random.default_rng(0))
for name, g in (("wls", va.wls), ("graph", va.graph)):
    ok = np.isfinite(g).all(1)
    e = np.abs(ned_errors(g[ok], va.truth[ok]))   # NED frame of the truth, as every other metric
    print(f"validation n={ok.sum()} zero-correction MAE N/E/D at {name}: " + " / ".join(f"{v:.2f}" for v in e.mean(0)))
