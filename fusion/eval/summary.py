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


def run_summary(record: dict) -> str:
    """The lines ``gnssfuse run`` prints from a run record (:func:`fusion.io.estimates.run_record`)."""
    lines = [f"{record['trace']}: {record['epochs_solved']}/{record['epochs_total']} epochs solved in mode "
             f"{record['mode']}; skipped while loading: {skip_words(record['skipped'])}"]
    info = record["info"]
    if info.get("excluded_measurements") or info.get("epochs_fault_undecided"):
        lines.append(f"WLS fault detection: {info['excluded_measurements']} measurements excluded in "
                     f"{info['epochs_with_exclusions']} epochs; {info['epochs_fault_undecided']} epochs undecided"
                     " (see metrics.json 'info'; --wls-plain for the plain baseline)")
    if info.get("guard_shrunk"):
        lines.append(f"out-of-distribution guard: the network's correction shrunk in {info['guard_shrunk']} "
                     f"epochs, switched off in {info.get('guard_off', 0)}")
    lines.append(DATUM)
    return "\n".join(lines)
