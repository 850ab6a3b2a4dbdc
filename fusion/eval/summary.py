"""Counts and outcomes in words, for what the command line prints and the report states (light:
no plotting imports, so ``gnssfuse run`` and training can use it)."""
from __future__ import annotations


#: The height datum, stated wherever heights are shown or written.
DATUM = ("Positions are WGS84; heights are ellipsoidal (above the WGS84 ellipsoid, not mean sea level), "
         "in estimates.csv and in every export.")


def _reason_words(key: str) -> str:
    """``rows_nonnumeric:rawPrM`` -> ``rows nonnumeric (rawPrM)``."""
    reason, _, column = key.partition(":")
    return reason.replace("_", " ") + (f" ({column})" if column else "")


def skip_words(skipped: dict[str, int]) -> str:
    """What a loader skipped, in words: ``84 conflicting duplicate rows, 2 rows nonnumeric (rawPrM)``;
    ``nothing`` when empty."""
    items = sorted((k, int(v)) for k, v in skipped.items() if int(v))
    return ", ".join(f"{v} {_reason_words(k)}" for k, v in items) or "nothing"


def learned_words(info: dict) -> str:
    """What the network and its guard did (a mode's ``learned_*`` info), in words."""
    g = {k[len("learned_"):]: int(v) for k, v in info.items() if k.startswith("learned_") and isinstance(v, (int, float))}
    who = f"ensemble of {g['members']} networks (guard counts: the most of any)" if g.get("members") else "network"
    if g.get("sigma_passes", 1) > 1:
        who += (f", asked {g['sigma_passes']} times for the pseudorange sigmas (measurement counts: the last pass's;"
                " epoch counts: the first's, whose prior the graph takes)")
    extra = ""
    if "prior_widened" in g:
        extra = (f"; its prior widened in {g['prior_widened']} epochs, where the pseudorange residuals exceed their "
                 f"model (median variance factor {float(info.get('learned_prior_factor_p50', 0.0)):.2f})")
    if g.get("prior_withheld"):
        extra += (f"; its prior withheld at {g['prior_withheld']} epochs the graph without it cannot place (too few "
                  "satellites: the prior alone would place them, asked at a guess interpolated across the gap)")
    if g.get("epochs_few_satellites"):
        extra += (f"; its pseudorange sigmas left to the physical model at {g['epochs_few_satellites']} epochs of too "
                  "few satellites to judge one against the others")
    if "carrier_sigmas_raised" in g:
        extra += (f"; {g['carrier_sigmas_raised']} carrier-phase differences given at least twice their sigma, "
                  "their satellites' pseudoranges distrusted (a reflection's carrier follows its path)")
    return (f"{who}: asked at {g.get('epochs_asked', 0)} epochs, {g.get('meas_asked', 0)} measurements; its guard "
            f"gave the physical sigma model {g.get('meas_out_of_range', 0)} measurements with inputs outside the "
            f"training range; {g.get('meas_unseen_signal', 0)} measurements of signals it cannot read left to the "
            f"graph's own model; {g.get('meas_signal_read_as_unknown', 0)} read as an unknown signal (one it was "
            f"not trained on); correction shrunk in {g.get('epochs_guard_shrunk', 0)} epochs, switched off in "
            f"{g.get('epochs_guard_off', 0)}{extra}")


def move_words(info: dict) -> str:
    """How far the network moved the solution from the answer without it, in words."""
    return (f"the network moved the solution by {info['learned_move_h_p50_m']:.2f} m horizontally at the median "
            f"epoch ({info.get('learned_move_h_p95_m', 0.0):.2f} m at the 95th percentile) from the answer without it")


def doppler_head_words(info: dict) -> str:
    """What the learned Doppler head and its guard did, in words."""
    g = {k: int(info.get(f"learned_doppler_{k}", 0)) for k in ("sigmas", "unseen_system", "out_of_range",
                                                                "likely_outliers")}
    return (f"Doppler head: sigmas of {g['sigmas']} pseudorange rates ({g['likely_outliers']} likely outliers); "
            f"its guard left the physical model to {g['out_of_range']} with inputs outside the training range and "
            f"{g['unseen_system']} of constellations it never saw")


def bridged_words(info: dict) -> str:
    """The graph's epochs that only the motion model placed, and those whose sigmas their check widened, in
    words."""
    widened = info.get("bridged_widened")
    checked = (f"; the sigmas of {widened} widened where the graph without Doppler and carrier disagreed"
               if widened else "")
    return (f"{info['epochs_bridged']} epochs bridged by the motion model (fewer than 4 satellites and no prior but "
            f"the network's, which reads those same satellites; longest stretch {info.get('longest_bridge_s', 0):.0f} s"
            f"{checked}): column 'bridged' in estimates.csv")


def incremental_words(info: dict) -> str:
    """What the incremental smoother left out or solved twice (``incremental_unanchored``, ``incremental_retried``),
    in words; empty where it did neither."""
    said = []
    if info.get("incremental_unanchored"):
        said.append(f"{info['incremental_unanchored']} epochs left out (a stretch with no epoch of four satellites "
                    "or a prior without pseudoranges to start it; the batch solver, without --incremental, places "
                    "what the motion model can)")
    if info.get("incremental_retried"):
        said.append("solved a second time, where ISAM2 found the system singular: carrier-phase pairs counted by "
                    "satellite, not by signal, and each carrier clock held loosely at the code clock")
    return "incremental smoother: " + "; ".join(said) if said else ""


#: what a mode's learned parts did, in words, where its info has the key
LEARNED_WORDS = (("learned_epochs_asked", learned_words), ("learned_move_h_p50_m", move_words),
                 ("learned_doppler_sigmas", doppler_head_words))


def run_summary(record: dict) -> str:
    """The lines ``gnssfuse run`` prints from a run record (:func:`fusion.io.estimates.run_record`)."""
    lines = [f"{record['trace']}: {record['epochs_solved']}/{record['epochs_total']} epochs solved in mode "
             f"{record['mode']}; skipped while loading: {skip_words(record['skipped'])}"]
    info = record["info"]
    if info.get("excluded_measurements") or info.get("epochs_fault_undecided"):
        lines.append(f"WLS fault detection: {info['excluded_measurements']} measurements excluded in "
                     f"{info['epochs_with_exclusions']} epochs; {info['epochs_fault_undecided']} epochs undecided"
                     " (see metrics.json 'info'; --wls-plain for the plain baseline)")
    lines += [words(info) for key, words in LEARNED_WORDS if key in info]
    raised = {k: int(info.get(f"{k}_sigmas_raised", 0)) for k in ("pseudorange", "doppler", "carrier")}
    if any(raised.values()):
        lines.append("sigmas raised where the measurements disagreed among themselves beyond them: "
                     + ", ".join(f"{n} {k}" for k, n in raised.items() if n) + " (metrics.json 'info')")
    if info.get("doppler_drift_jump_mps"):
        lines.append("the receiver clock's drift, as the Doppler shows it, jumps around its course by "
                     f"{info['doppler_drift_jump_mps']:.2f} m/s (1 sigma) each epoch: each epoch's Doppler got a "
                     "drift of its own")
    if info.get("epochs_bridged"):
        lines.append(bridged_words(info))
    if said := incremental_words(info):
        lines.append(said)
    m = record.get("metrics") or {}
    if "within1sigma_n" in m:
        lines.append("errors within the mode's 1 sigma, N / E / D: "
                     + " / ".join(f"{m[f'within1sigma_{a}']:.2f}" for a in "ned") + " (a Gaussian: 0.68)")
    if info.get("carrier_calibrated"):
        lines.append(f"sigmas of the {info['carrier_calibrated']} epochs carrier phase ties to a neighbour: calibrated "
                     "as such (a metre's floor for what broadcast corrections leave)")
    if record.get("covariance") is False:
        why = " (the graph was singular at ISAM2's estimate)" if info.get("incremental_no_marginals") else ""
        lines.append(f"no covariance from this run{why}: estimates.csv has no sigma columns, and a .pos export "
                     "writes 0 for them, RTKLIB's 'unknown'")
    lines.append(DATUM)
    return "\n".join(lines)
