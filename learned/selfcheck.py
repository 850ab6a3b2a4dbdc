"""Self-validation of an adaptation on the log itself, without ground truth.

The teacher-trusted epochs of each log are cut into blocks of ``block`` consecutive samples; every
``every``-th block (the second of each group, so a short log still holds one out) is held out of the
fine-tuning. On the held-out epochs the criterion is the leave-one-satellite-out prediction error of the
pseudoranges: each satellite predicted from the position and clock the *others* give when weighted by
the network's sigmas (:func:`learned.consistency.loo_residuals`, asked at the teacher as ``fused`` asks),
its absolute residual capped at ``CAP`` m (a NLOS satellite's tens of metres would drown the rest) and
averaged. The learned biases are deliberately left out: a bias head that copies the teacher's residuals
would make every satellite agree with the teacher, not with the truth; and the sigmas' overall scale
cannot lower it (a weighted solution does not move when all weights scale), so a head that merely shrinks
its sigmas gains nothing. It scores only what the weighting does to the others' solution.

Measured before fine-tuning and after each epoch; the best epoch is kept only if it is at least
``margin`` (relative) below the base's, else the adaptation is declined. Nothing here reads truth: the
split and the criterion use the samples' measurements and the teacher in their ``truth`` slot.
"""
from __future__ import annotations

import numpy as np
import torch

from learned.consistency import loo_residuals
from learned.data import Samples
from learned.features import FeatureConfig
from learned.forward import outputs, take
from learned.train import make_inputs

#: Defaults of the split and of the acceptance margin (relative gain of the held-out criterion). The margin:
#: on the twelve GSDC drives adapted from the cross-validation network that never saw them, gains of 0.7-1.6 %
#: were followed by -1.3 to +4.5 % in `fused` (06-05-MTV-1: 1.6 % -> 4.5 % worse), and the one larger gain
#: (smartLoc, 3 %) paid 9 %; 2 %, the least of 0.5 / 1 / 1.5 / 2 % with no tuning log worse than 1.02 x
#: (``experiments/results/adapt.md``).
BLOCK, EVERY, MARGIN = 60, 4, 0.02
#: The held-out figure of :func:`criteria` the decision reads, and its residual cap [m].
CRITERION, CAP = "huber_nb", 10.0


def holdout_mask(samples: Samples, block: int = BLOCK, every: int = EVERY) -> np.ndarray:
    """(N,) bool, True for held-out samples: block ``b`` (of ``block`` consecutive samples of one trace,
    samples being in trace order) is held out when ``b % every == 1``."""
    n = len(samples)
    pos_in_trace = np.arange(n) - np.searchsorted(samples.trace, samples.trace, side="left")
    return (pos_in_trace // block) % every == 1


def split(samples: Samples, block: int = BLOCK, every: int = EVERY) -> tuple[Samples, Samples]:
    """(fine-tuning samples, held-out samples) by :func:`holdout_mask`."""
    held = holdout_mask(samples, block, every)
    return samples.subset(np.flatnonzero(~held)), samples.subset(np.flatnonzero(held))


def heldout_inputs(tensors: dict, fcfg: FeatureConfig) -> dict:
    """Network inputs of the held-out sample tensors at the teacher (the ``graph`` guess source)."""
    return make_inputs(tensors, tensors["graph"], fcfg)


@torch.no_grad()
def criteria(model, inp: dict, fcfg: FeatureConfig, batch: int = 1024) -> dict:
    """Held-out leave-one-satellite-out figures over pseudoranges of epochs with >= 5 satellites, with the
    model's sigmas, with its biases (``nll``, mean NLL; ``mae``, ``med``: mean / median |residual| [m];
    ``huber``: mean of min(|residual|, CAP)) and without them (``*_nb``). Recorded beside the decision,
    so that the choice of criterion can be revisited."""
    model.eval()
    es, nll, e0s, nll0 = [], [], [], []
    for a in range(0, inp["x"].shape[0], batch):
        b = take(inp, torch.arange(a, min(a + batch, inp["x"].shape[0])))
        out = outputs(model, b, fcfg)
        e, var, use = loo_residuals(b["sat_pos"], b["pr"], b["mask"], b["truth"], out["sigma"], out["bias"])
        es.append(e[use])
        nll.append((0.5 * torch.log(var) + 0.5 * e ** 2 / var)[use])
        e0, var0, _ = loo_residuals(b["sat_pos"], b["pr"], b["mask"], b["truth"], out["sigma"],
                                    torch.zeros_like(out["bias"]))
        e0s.append(e0[use])
        nll0.append((0.5 * torch.log(var0) + 0.5 * e0 ** 2 / var0)[use])
    e, nll, e0, nll0 = torch.cat(es).abs(), torch.cat(nll), torch.cat(e0s).abs(), torch.cat(nll0)
    if not e.numel():
        return dict.fromkeys(("nll", "mae", "med", "huber", "mae_nb", "nll_nb", "huber_nb"), float("nan"))
    return {"nll": float(nll.mean()), "mae": float(e.mean()), "med": float(e.median()),
            "huber": float(e.clamp_max(CAP).mean()), "mae_nb": float(e0.mean()), "nll_nb": float(nll0.mean()),
            "huber_nb": float(e0.clamp_max(CAP).mean())}


def decide(scores: list[float], margin: float) -> tuple[int, str]:
    """Best epoch (0: the base) and the reason, from the held-out criterion ``scores`` (base first)."""
    if len(scores) < 2 or not np.isfinite(scores[0]):
        return 0, "no held-out epoch with >= 5 satellites to validate on"
    if scores[0] <= 0:
        return 0, "the base already predicts every held-out pseudorange exactly: nothing to gain"
    finite = [s if np.isfinite(s) else np.inf for s in scores]
    best = int(np.argmin(finite[1:])) + 1
    gain = 1.0 - finite[best] / scores[0]
    what = f"held-out leave-one-satellite-out error {scores[0]:.3f} m (base) -> {finite[best]:.3f} m (epoch {best})"
    if not gain >= margin:
        return 0, f"{what}: gain {gain:.2%} < margin {margin:.2%}"
    return best, f"{what}: gain {gain:.2%} >= margin {margin:.2%}"
