"""The graph's velocity as ``estimates.csv`` writes it (``vel_n_mps`` ...), against the truth and against the
difference of the track's own positions (what RMC's speed was before the graph's velocity was written).

The truth's velocity is the central difference of the reference receiver's 10 Hz positions (its SPAN NMEA log),
interpolated to the receiver epochs: a velocity over 0.2 s, where the track's own difference spans two seconds at
1 Hz. Horizontal error |v - v_truth| over the epochs where both exist; the Pixel5 RINEX test trace (Doppler and
carrier; reported, nothing tuned on it) and a GSDC 2021 derived file (no Doppler: the motion model alone gives
the velocity). For the velocity ``estimates.csv`` writes, also the share of its errors within its written 1 and
2 sigma per axis (a Gaussian: 0.68 and 0.95). Where RTKLIB is installed, the velocity its single-point
solution estimates from the same log's Doppler (``rnx2rtkp -p 0`` with ``out-outvel = on``) at its own epochs.

    python experiments/velocity_output.py
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "experiments"))

from few_satellites import NAV, PIXEL5, SHARED  # noqa: E402
from fusion.eval.metrics import within_sigma  # noqa: E402
from fusion.geometry import ecef2ned_vec, geodetic2ecef, ned2ecef_vec  # noqa: E402
from fusion.io.rtklib_pos import read_pos_at  # noqa: E402
from fusion.io.nmea import read_span_nmea  # noqa: E402
from fusion.modes import run_modes, solve_initial  # noqa: E402
from fusion.options import load_options  # noqa: E402
from fusion.prepare.load import load_trace  # noqa: E402
from fusion.run_types import RunOptions  # noqa: E402

GSDC = SHARED / "gsdc2021" / "train" / "2020-05-14-US-MTV-1" / "Pixel4"
MODES = ("fused-nodnn", "fused")


def central_difference(t_s: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """(E,3) velocity [m/s] of positions (E,3) by central differences (one-sided at the ends)."""
    return np.gradient(pos, t_s, axis=0)


def horizontal_errors(v: np.ndarray, v_ref: np.ndarray, at: np.ndarray) -> np.ndarray:
    """(n,) horizontal |v - v_ref| [m/s] where both (E,3) ECEF are finite, in the NED frame at ``at`` (E,3)."""
    ok = np.isfinite(v).all(axis=1) & np.isfinite(v_ref).all(axis=1) & np.isfinite(at).all(axis=1)
    ned = ecef2ned_vec(v[ok] - v_ref[ok], at[ok])
    return np.hypot(ned[:, 0], ned[:, 1])


def truth_velocity(folder: Path, t_ms: np.ndarray) -> np.ndarray:
    """(E,3) ECEF velocity [m/s] of the folder's 10 Hz SPAN log at the times ``t_ms`` (E,) (GPS ms)."""
    span = read_span_nmea(next((folder / "supplemental").glob("SPAN_*.nmea")))
    v = central_difference(span.t_ms.to_numpy() / 1000.0,
                           geodetic2ecef(span[["lat_deg", "lon_deg", "height_m"]].to_numpy(float)))
    return np.column_stack([np.interp(t_ms, span.t_ms, v[:, i], left=np.nan, right=np.nan) for i in range(3)])


def rows(name: str, folder: Path, opts: RunOptions) -> list[str]:
    trace = load_trace(folder, **load_options(opts))
    t = trace.t_ms / 1000.0
    truth_v = truth_velocity(folder, trace.t_ms)
    results = run_modes(trace, list(MODES), opts, wls=solve_initial(trace, opts))
    out = []
    for mode, res in results.items():
        for what, v in (("graph velocity", res.info["vel"]), ("track difference", central_difference(t, res.pos))):
            h = horizontal_errors(v, truth_v, trace.truth)
            out.append(f"| {name} | {mode} | {what} | {np.percentile(h, 50):.3f} | {np.percentile(h, 95):.3f} | "
                       f"{len(h)} | {sigma_shares(res, truth_v) if what == 'graph velocity' else '-'} |")
    return out


def sigma_shares(res, truth_v: np.ndarray) -> str:
    """Share of the velocity's errors within its 1 and 2 sigma, N / E / D, at the epochs ``estimates.csv`` writes
    them (where Doppler measures the velocity; "-": no marginals)."""
    vel_cov, measured = res.info.get("vel_cov"), res.info.get("doppler_epochs")
    if vel_cov is None or measured is None or not measured.any():
        return "-"
    ok = measured & np.isfinite(res.pos).all(axis=1) & np.isfinite(truth_v).all(axis=1)
    w = within_sigma(ecef2ned_vec(res.info["vel"][ok] - truth_v[ok], res.pos[ok]), res.pos[ok], vel_cov[ok])
    share = lambda k: " / ".join(f"{w[f'within{k}sigma_{ax}']:.2f}" for ax in "ned")   # noqa: E731
    return f"{share(1)} ({share(2)})"


def rtklib_velocity(obs: Path, nav: Path, t_ms: np.ndarray, at: np.ndarray) -> np.ndarray | None:
    """(E,3) ECEF velocity [m/s] of RTKLIB's single-point solution at the epochs ``t_ms`` (E,) (NaN where it
    gives none), its east/north/up turned at ``at`` (E,3); None without ``rnx2rtkp``."""
    exe = shutil.which("rnx2rtkp")
    if exe is None:
        return None
    with tempfile.TemporaryDirectory() as tmp:
        conf, pos = Path(tmp) / "vel.conf", Path(tmp) / "rtk.pos"
        conf.write_text("out-outvel =on\nout-timeform =tow\n")
        subprocess.run([exe, "-k", str(conf), "-p", "0", "-o", str(pos), str(obs), str(nav)], capture_output=True,
                       check=True)
        # after lat, lon, h, Q, ns, six sigmas, age and ratio: vn, ve, vu; -vu is down
        v = read_pos_at(pos, t_ms)[:, 13:16] * np.array([1.0, 1.0, -1.0])
    have = np.isfinite(v).all(axis=1) & np.isfinite(at).all(axis=1)
    v[have] = ned2ecef_vec(v[have], at[have])
    return v


def rtklib_row(name: str, folder: Path, opts: RunOptions) -> str:
    """The table's row for RTKLIB's single-point velocity on the log (a note without ``rnx2rtkp``)."""
    trace = load_trace(folder, **load_options(opts))
    v = rtklib_velocity(next((folder / "supplemental").glob("*.21o")), opts.nav[0], trace.t_ms, trace.truth)
    if v is None:
        return f"| {name} | RTKLIB rnx2rtkp -p 0 | not installed (apt-get install rtklib) | - | - | - | - |"
    h = horizontal_errors(v, truth_velocity(folder, trace.t_ms), trace.truth)
    return (f"| {name} | RTKLIB rnx2rtkp -p 0 | its Doppler velocity | {np.percentile(h, 50):.3f} | "
            f"{np.percentile(h, 95):.3f} | {len(h)} | - |")


def main() -> int:
    print("| trace | mode | velocity | horizontal error p50 [m/s] | p95 [m/s] | epochs | within 1 (2) sigma, N / E / D "
          "|\n|---|---|---|---|---|---|---|")
    pixel5 = RunOptions(signals=None, nav=(NAV,))
    for line in rows("Pixel5 RINEX, broadcast GPS", PIXEL5, pixel5):
        print(line)
    print(rtklib_row("Pixel5 RINEX, broadcast GPS", PIXEL5, pixel5))
    for line in rows("2020-05-14-US-MTV-1 Pixel4 (no Doppler)", GSDC, RunOptions()):
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
