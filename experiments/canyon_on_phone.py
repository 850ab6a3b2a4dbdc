"""A street canyon laid over a real phone log: does Doppler and carrier still help the graph, and the learned
part `fused`, when a phone's own measurements meet buildings?

The Pixel5 RINEX test trace (a suburban drive, broadcast GPS L1 + L5) keeps its real noise, Doppler and carrier;
the simulator's canyon (:mod:`fusion.sim.canyon`: random streets along the true track, building masks) then
removes the satellites the buildings block and, where only a reflection arrives (NLOS) or the signal bends over a
roof edge, adds the extra path to the pseudorange and the carrier, its rate to the Doppler, and the loss to the
C/N0; the carrier's chain breaks where a satellite changes class (a slip). The truth places the streets only;
nothing learned or solved sees it. Seeded street layouts; GSDC score [m].

    python experiments/canyon_on_phone.py [--seeds 0 1 2] [--height 15 60] [--width 15 35] [--no-doppler-jump]
        [--sp3] [--signals GPS_L1,GLO_G1,GAL_E1] [--graph-config FILE.toml]

``--sp3``: CODE's multi-GNSS SP3/CLK (GPS, GLONASS and Galileo, every signal the log has unless ``--signals``
names some) instead of the broadcast GPS file.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from few_satellites import NAV, PIXEL5  # noqa: E402
from pixel5_table import ORBITS  # noqa: E402
from fusion.estimate.graph.config import load_graph_config  # noqa: E402
from fusion.eval.metrics import mode_metrics  # noqa: E402
from fusion.geometry import elevation_azimuth, line_of_sight  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import add_signals_option, load_options, parse_signals  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402
from fusion.sim.canyon import BLOCKED, LOS, CanyonModel, classify, street_layout  # noqa: E402
from fusion.sim.cn0 import Cn0Model, draw_cn0, los_cn0  # noqa: E402
from fusion.trace import Trace  # noqa: E402

#: the deep canyon of the experiments (``--height 30 100 --width 12 25``): a high-rise core
DEEP = CanyonModel(height_m=(30.0, 100.0), width_m=(12.0, 25.0))


def canyon_classes(trace: Trace, model: CanyonModel, seed: int) -> dict[str, np.ndarray]:
    """:func:`fusion.sim.canyon.classify` of every slot (E,S) of ``trace`` from seeded streets of ``model``
    laid along its true track."""
    rng = np.random.default_rng(seed)
    start = np.zeros(trace.n_epochs, bool)
    start[0] = True
    layout = street_layout(trace.truth, start, model, rng)
    vel_ne = np.gradient(layout["ne"], trace.t_ms / 1000.0, axis=0)
    _, los = line_of_sight(trace.sat_pos, trace.truth)
    el, az = elevation_azimuth(los, trace.truth)
    return classify(el, az, layout, vel_ne, model, cols=trace.sat_id)


def reflected(trace: Trace, c: dict[str, np.ndarray]) -> np.ndarray:
    """(E,S) bool real slots that arrive reflected or bent (not blocked, not line of sight) by classes ``c``."""
    return trace.mask & (c["cls"] != LOS) & (c["cls"] != BLOCKED)


def with_model_cn0(trace: Trace, seed: int) -> Trace:
    """``trace`` with a C/N0 drawn from the simulator's line-of-sight model (:mod:`fusion.sim.cn0`: signal power,
    path loss and antenna pattern at the truth's geometry, a receiver offset, an offset per satellite and noise),
    for logs whose files carry none (the GSDC 2021 derived files); :func:`in_canyon` then lowers it for
    reflections. Its real slots' C/N0 only; nothing else changes."""
    rng, model = np.random.default_rng(seed), Cn0Model()
    rng_m, los = line_of_sight(trace.sat_pos, trace.truth)
    el, _ = elevation_azimuth(los, trace.truth)
    # slots are packed per epoch, so the satellite offset is looked up by satellite, not by column
    ids, of_slot = np.unique(trace.sat_id, return_inverse=True)
    sat_db = (rng.standard_normal(ids.size) * model.satellite_sigma_db)[of_slot.reshape(trace.sat_id.shape)]
    cn0 = draw_cn0(np.nan_to_num(los_cn0(trace.signal.astype(int), el, rng_m, model)) + sat_db,
                   np.zeros(trace.n_epochs, int), replace(model, satellite_sigma_db=0.0), rng)
    return replace(trace, cn0=np.where(trace.mask, cn0, 0.0))


def in_canyon(trace: Trace, model: CanyonModel, seed: int) -> tuple[Trace, dict[str, float]]:
    """``trace`` seen from streets of ``model`` along its true track (module docstring), and the shares of its
    measurements blocked and reflected or bent."""
    c = canyon_classes(trace, model, seed)
    real = trace.mask
    blocked = real & (c["cls"] == BLOCKED)
    bent = reflected(trace, c)
    changed = class_changed(trace, c["cls"])
    out = replace(trace, pr=trace.pr + np.where(bent, c["delay_m"], 0.0), mask=real & ~blocked,
                  cn0=None if trace.cn0 is None else np.where(bent, trace.cn0 - c["loss_db"], trace.cn0),
                  prr=None if trace.prr is None else trace.prr + np.where(bent, c["rate_err_mps"], 0.0),
                  adr=None if trace.adr is None else trace.adr + np.where(bent, c["delay_m"], 0.0),
                  adr_slip=None if trace.adr_slip is None else trace.adr_slip | changed)
    n = max(int(real.sum()), 1)
    return out, {"blocked": blocked.sum() / n, "reflected": bent.sum() / n}


def class_changed(trace: Trace, cls: np.ndarray) -> np.ndarray:
    """(E,S) bool: the slot's satellite and signal had another class (:func:`classify`) in its previous epoch
    (slots are packed per epoch, so a measurement is followed by its satellite and signal, not its slot)."""
    e, s = np.nonzero(trace.mask)
    ident = trace.sat_id[e, s].astype(np.int64) * 64 + trace.signal[e, s]
    order = np.lexsort((e, ident))                         # each measurement after its predecessor
    same = ident[order][1:] == ident[order][:-1]
    c = cls[e, s][order]
    out = np.zeros(trace.mask.shape, bool)
    nxt = order[1:][same & (c[1:] != c[:-1])]
    out[e[nxt], s[nxt]] = True
    return out


def scores(trace: Trace, opts: RunOptions) -> tuple[dict[str, float], str]:
    """GSDC score of wls; fused-nodnn with pseudoranges only, + Doppler, + carrier, + both; fused with both;
    and the Doppler drift jump the graph with both took from the log [m/s] ("-": none taken)."""
    wls = solve_initial(trace, opts)
    out = {"wls": run_modes(trace, ["wls"], opts, wls=wls)["wls"]}
    for name, doppler, carrier in (("pseudoranges only", False, False), ("+ Doppler", True, False),
                                   ("+ carrier", False, True)):
        o = replace(opts, graph=replace(opts.graph, use_doppler=doppler, use_carrier=carrier))
        out[f"fused-nodnn, {name}"] = run_modes(trace, ["fused-nodnn"], o, wls=wls)["fused-nodnn"]
    both = run_modes(trace, ["fused-nodnn", "fused"], opts, wls=wls)
    out.update({"fused-nodnn, + Doppler and carrier": both["fused-nodnn"], "fused, + Doppler and carrier": both["fused"]})
    jump = both["fused-nodnn"].info.get("doppler_drift_jump_mps")
    return {k: mode_metrics(trace, r)["gsdc_score"] for k, r in out.items()}, "-" if jump is None else f"{jump:.2f}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--height", type=float, nargs=2, default=(15.0, 60.0), help="building heights [m], lo hi")
    p.add_argument("--width", type=float, nargs=2, default=(15.0, 35.0), help="street widths [m], lo hi")
    p.add_argument("--no-doppler-jump", action="store_true",
                   help="the Doppler sees the drift state itself, without the jump the log shows "
                        "(GraphConfig.doppler_jump_from_log off)")
    p.add_argument("--sp3", action="store_true", help="multi-GNSS SP3/CLK instead of broadcast GPS")
    p.add_argument("--graph-config", type=Path, default=None, metavar="FILE.toml",
                   help="the graph's settings (GraphConfig fields as 'name = value' lines; default: the shipped)")
    add_signals_option(p, "default: every signal the orbits cover")
    args = p.parse_args()
    orbits = ORBITS["CODE SP3/CLK, multi-GNSS (+ hour1180.21n ionosphere)"] if args.sp3 else {"nav": (NAV,)}
    opts = RunOptions(signals=parse_signals(args.signals), sigma_calibration=False, **orbits)
    if args.graph_config is not None:
        opts = replace(opts, graph=load_graph_config(args.graph_config))
    if args.no_doppler_jump:
        opts = replace(opts, graph=replace(opts.graph, doppler_jump_from_log=False))
    trace = load_trace(PIXEL5, min_sats=1, **load_options(opts))
    model = CanyonModel(height_m=tuple(args.height), width_m=tuple(args.width))
    rows = [("as logged", {"blocked": 0.0, "reflected": 0.0}, *scores(trace, opts))]
    for seed in args.seeds:
        canyon, share = in_canyon(trace, model, seed)
        rows.append((f"canyon, streets seed {seed}", share, *scores(canyon, opts)))
    keys = list(rows[0][2])
    print("| Pixel5 RINEX | blocked | reflected or bent | Doppler drift jump [m/s] | " + " | ".join(keys) + " |")
    print("|---|---|---|---|" + "---|" * len(keys))
    for name, share, s, jump in rows:
        print(f"| {name} | {share['blocked']:.2f} | {share['reflected']:.2f} | {jump} | "
              + " | ".join(f"{s[k]:.2f}" for k in keys) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
