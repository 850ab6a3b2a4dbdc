"""Figures for ``gnssfuse evaluate``: error CDFs, quantile box plots, trajectories, error vs time.

Every function takes plain arrays keyed by mode name, writes one PNG and returns its path, so
adding a mode never needs a change here. Errors are NED metres (north, east, down) as returned by
:func:`fusion.eval.metrics.ned_errors`; NaN rows (unsolved epochs or epochs without truth) are ignored.
Matplotlib runs headless (Agg); figures are closed after saving so long runs do not leak memory.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from fusion.geometry import ecef2ned_vec  # noqa: E402
from fusion.eval.metrics import cdf, horizontal  # noqa: E402

AXES = ("north", "east", "down")
#: Upper percentile shown on CDF x-axes; a few extreme outliers would otherwise squash the curves.
CDF_CLIP_PCT = 99.0


def _finite_rows(a: np.ndarray) -> np.ndarray:
    return a[np.isfinite(a).all(axis=-1)] if a.ndim == 2 else a[np.isfinite(a)]


def _break_gaps(t: np.ndarray | None, y: np.ndarray, max_gap: float) -> tuple[np.ndarray | None, np.ndarray]:
    """Insert a NaN row wherever consecutive times differ by more than ``max_gap``, so lines are
    not drawn across data gaps (e.g. the separate windows of one drive). y: (E,) or (E, k)."""
    if t is None or len(t) < 2:
        return t, y
    cut = np.flatnonzero(np.diff(t) > max_gap) + 1
    return np.insert(t.astype(float), cut, np.nan), np.insert(y.astype(float), cut, np.nan, axis=0)


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # a figure with a layout engine is laid out already; "tight" would draw it a second time
    fig.savefig(path, dpi=110, bbox_inches=None if fig.get_layout_engine() else "tight")
    plt.close(fig)
    return path


def _no_data(ax, text: str = "no epochs with truth") -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")


def plot_error_cdfs(errors: dict[str, np.ndarray], path: Path, title: str = "",
                    clip_pct: float = CDF_CLIP_PCT) -> Path:
    """CDFs of |north|, |east|, |down| and horizontal error, one curve per mode.

    errors: mode -> (E, 3) NED error [m]. The x-range of each panel stops at the ``clip_pct``
    percentile over all modes (the curves themselves use every epoch); the panel says so.
    """
    fig, axs = plt.subplots(1, 4, figsize=(16, 3.8), layout="constrained")
    panels = [(f"|{a}| error [m]", lambda e, i=i: np.abs(e[:, i])) for i, a in enumerate(AXES)]
    panels.append(("horizontal error [m]", horizontal))
    for ax, (label, fn) in zip(axs, panels):
        vals = {m: fn(_finite_rows(e)) for m, e in errors.items()}
        pooled = np.concatenate([v for v in vals.values()] + [np.zeros(0)])
        if pooled.size == 0:
            _no_data(ax)
        for mode, v in vals.items():
            if v.size:
                x, p = cdf(v)
                ax.step(x, p, where="post", label=f"{mode} (n={v.size})")
        if pooled.size:
            hi = float(np.percentile(pooled, clip_pct))
            ax.set_xlim(0, hi * 1.02 if hi > 0 else 1.0)
            n_out = int((pooled > hi).sum())
            ax.set_title(f"x clipped at p{clip_pct:g} ({n_out} pts beyond)", fontsize=9)
        ax.set_xlabel(label)
        ax.set_ylim(0, 1.0)
        ax.grid(alpha=0.3)
    axs[0].set_ylabel("fraction of epochs")
    if axs[-1].get_legend_handles_labels()[0]:
        axs[-1].legend(loc="lower right", fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def plot_error_boxes(errors: dict[str, np.ndarray], path: Path, title: str = "") -> Path:
    """Quantile box plots of signed N/E/D errors per mode (as in Kanhere et al., Fig. 5).

    Box Q1-Q3 with the median; whiskers at the furthest point within 1.5*IQR; points beyond
    them drawn as outliers. The y-range covers every whisker with a margin; outliers outside it
    are counted in the panel title rather than allowed to flatten the boxes.
    """
    modes = list(errors)
    fig, axs = plt.subplots(1, 3, figsize=(4.2 * 3, 4.2), layout="constrained")
    for i, (ax, axis) in enumerate(zip(axs, AXES)):
        data = [_finite_rows(errors[m])[:, i] for m in modes]
        keep = [(m, d) for m, d in zip(modes, data) if d.size]
        if not keep:
            _no_data(ax)
            ax.set_title(f"{axis} error")
            continue
        labels, arrays = zip(*keep)
        ax.boxplot(arrays, whis=1.5, showfliers=True, tick_labels=labels,
                   flierprops=dict(marker=".", markersize=3, alpha=0.5))
        lo, hi = box_limits(arrays)
        n_out = sum(int(((d < lo) | (d > hi)).sum()) for d in arrays)
        ax.set_ylim(lo, hi)
        ax.axhline(0.0, color="0.5", lw=0.8, ls=":")
        ax.set_title(f"{axis} error" + (f" ({n_out} outlier{'s' if n_out > 1 else ''} off-scale)" if n_out else ""), fontsize=10)
        ax.set_ylabel(f"{axis} error [m]")
        ax.grid(axis="y", alpha=0.3)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


def box_limits(arrays, whis: float = 1.5, pad: float = 0.5) -> tuple[float, float]:
    """y-range covering every box's whiskers (furthest points within ``whis``*IQR), plus
    ``pad`` times that span on each side, so a few huge outliers cannot flatten the boxes."""
    lo, hi = np.inf, -np.inf
    for d in arrays:
        q1, q3 = np.percentile(d, [25, 75])
        iqr = q3 - q1
        inside = d[(d >= q1 - whis * iqr) & (d <= q3 + whis * iqr)]
        lo, hi = min(lo, inside.min()), max(hi, inside.max())
    margin = pad * max(hi - lo, 1e-3)
    return float(lo - margin), float(hi + margin)


def local_east_north(pos_ecef: np.ndarray, origin_ecef: np.ndarray) -> np.ndarray:
    """(E, 3) ECEF -> (E, 2) east, north [m] from ``origin_ecef`` in the NED frame at the origin."""
    ned = ecef2ned_vec(pos_ecef - origin_ecef, np.broadcast_to(origin_ecef, pos_ecef.shape))
    return ned[:, [1, 0]]


def plot_trajectories(positions: dict[str, np.ndarray], truth: np.ndarray | None, path: Path,
                      title: str = "", t_s: np.ndarray | None = None, max_gap_s: float = 5.0) -> Path:
    """Every mode's track over the truth in a local east/north frame.

    positions: mode -> (E, 3) ECEF with NaN rows where unsolved; truth: (E, 3) ECEF or None;
    t_s: (E,) epoch times [s], when given lines break across gaps longer than ``max_gap_s``.
    Origin: the first finite truth point, else the first solved estimate of any mode.
    """
    fig, ax = plt.subplots(figsize=(7, 7))
    candidates = ([truth] if truth is not None else []) + list(positions.values())
    origin = next((_finite_rows(c)[0] for c in candidates if len(_finite_rows(c))), None)
    if origin is None:
        _no_data(ax, "no solved epochs")
    else:
        def track(pos: np.ndarray) -> np.ndarray:
            ok = np.isfinite(pos).all(axis=1)   # skip unsolved epochs; break only at time gaps
            en = local_east_north(pos[ok], origin)
            return _break_gaps(None if t_s is None else t_s[ok], en, max_gap_s)[1]

        if truth is not None and len(_finite_rows(truth)):
            en = track(truth)
            ax.plot(en[:, 0], en[:, 1], color="k", lw=2.0, label="truth", zorder=1)
        for mode, pos in positions.items():
            if len(_finite_rows(pos)):
                en = track(pos)
                ax.plot(en[:, 0], en[:, 1], ".-", ms=2, lw=0.6, alpha=0.8, label=mode)
        ax.set_aspect("equal", adjustable="datalim")
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="best", fontsize=8)
    what = "first truth point" if truth is not None and len(_finite_rows(truth)) else "first estimate"
    ax.set_xlabel(f"east [m] from {what}")
    ax.set_ylabel(f"north [m] from {what}")
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title)
    return _save(fig, path)


def plot_error_vs_time(t_s: np.ndarray, errors: dict[str, np.ndarray], path: Path, title: str = "",
                       clip_pct: float = CDF_CLIP_PCT, max_gap_s: float = 5.0) -> Path:
    """Horizontal and vertical (down) error against time since the first epoch.

    t_s: (E,) seconds since the trace start; errors: mode -> (E, 3) NED [m]. The y-range stops at
    the ``clip_pct`` percentile of |error| over all modes, as in the CDFs. Lines break across time
    gaps longer than ``max_gap_s`` (unsolved single epochs are bridged).
    """
    fig, axs = plt.subplots(2, 1, figsize=(12, 6), sharex=True, layout="constrained")
    series = [("horizontal error [m]", horizontal),
              ("down error [m]", lambda e: e[:, 2])]
    for ax, (label, fn) in zip(axs, series):
        pooled = []
        for mode, e in errors.items():
            v = fn(e)
            ok = np.isfinite(v)
            if ok.any():
                t_b, v_b = _break_gaps(t_s[ok], v[ok], max_gap_s)
                ax.plot(t_b, v_b, lw=0.7, label=mode)
                pooled.append(np.abs(v[ok]))
        if pooled:
            pooled = np.concatenate(pooled)
            hi = float(np.percentile(pooled, clip_pct)) * 1.05 or 1.0
            ax.set_ylim((0, hi) if label.startswith("horizontal") else (-hi, hi))
            n_out = int((pooled > hi).sum())
            ax.text(0.99, 0.97, f"y clipped at p{clip_pct:g} of |error| ({n_out} pts beyond)", transform=ax.transAxes,
                    ha="right", va="top", fontsize=8, color="0.4")
            ax.legend(loc="upper left", fontsize=8)
        else:
            _no_data(ax)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axs[-1].set_xlabel("time since first epoch [s]")
    if title:
        fig.suptitle(title)
    return _save(fig, path)
