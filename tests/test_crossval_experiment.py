"""experiments/crossval.py's report: the pooled ratios printed to the millimetre."""
from __future__ import annotations

import numpy as np

from tests.experiment_module import experiment_module


def test_pooled_ratios_pool_every_fold_and_skip_a_pair_not_run():
    mod = experiment_module("crossval")
    rng = np.random.default_rng(0)
    errs = {m: [rng.normal(0, s, (200, 3)) for _ in range(4)] for m, s in (("fused-nodnn", 2.0), ("fused", 1.0))}
    results = {f: {f"d{i}": {m: {"err": errs[m][2 * j + i]} for m in errs} for i in range(2)}
               for j, f in enumerate(("AB", "CD"))}
    lines = mod.pooled_ratios(results)
    want = {m: mod.summarize(np.concatenate(errs[m]))["gsdc_score"] for m in errs}
    assert lines == [f"pooled fused / fused-nodnn: {want['fused']:.3f} / {want['fused-nodnn']:.3f} m = "
                     f"{want['fused'] / want['fused-nodnn']:.4f} x"]                  # dnn / wls not run: no line
