"""Pixel5 RINEX trace (2021-04-28-US-MTV-1/Pixel5) from raw observations: RINEX parse time, our
``wls``, ``fused-nodnn`` and ``fused`` (the shipped ensemble, and one of its networks) whole-process times and
GSDC scores, and RTKLIB ``rnx2rtkp -p 0``
(single point, its defaults) time and score, all in the same run with the same navigation file.

Whole process = a fresh ``python -m fusion.cli run`` (interpreter start, imports, RINEX + nav
parse, satellite states, truth, solve, estimates.csv + metrics.json) vs a fresh ``rnx2rtkp``
(parse, solve, write .pos). Each is scored by :mod:`fusion.eval.metrics` against the same truth
(the SPAN NMEA log interpolated at the receiver epochs); "epochs" is solved epochs with truth
over all receiver epochs with truth. Needs ``../shared/data`` (or ``$GNSSFUSE_SHARED_DATA``);
RTKLIB is skipped with a message when ``rnx2rtkp`` is not on PATH (``apt-get install rtklib``). The
package is byte-compiled first (:func:`compile_sources`), as a pip-installed one ships.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.run_all import JSON_PREFIX  # noqa: E402

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
TRACE = SHARED / "gsdc2021/train/2021-04-28-US-MTV-1/Pixel5"
OBS = TRACE / "supplemental/Pixel5_GnssLog.21o"
NAV = SHARED / "ephemeris/gps_nav/hour1180.21n"
PRECISE = SHARED / "ephemeris/precise"
SP3_ARGS = ["--sp3", str(PRECISE / "COD0MGXFIN_20211180000_01D_05M_ORB.SP3"),
            "--clk", str(PRECISE / "COD0MGXFIN_20211180000_01D_30S_CLK.CLK")]
NOTE = "2021-04-28-US-MTV-1/Pixel5 RINEX, nav hour1180.21n (GPS), 1985 epochs, CPU"
#: rounds of alternated timing (each command once per round, best round kept)
ROUNDS = 3


def _timed(cmd: list[str], env: dict | None = None) -> tuple[float, subprocess.CompletedProcess]:
    t = time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    dt = time.perf_counter() - t
    if out.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({out.returncode}): {out.stderr[-500:]}")
    return dt, out


def _truth():
    """(E,) receiver epochs [GPS ms] and (E, 3) truth of the trace, as the CLI loads them."""
    from fusion.prepare.load import load_trace
    from fusion.prepare.raw_load import RawSources

    tr = load_trace(TRACE, signals=None, min_sats=1, raw_sources=RawSources(nav=(NAV,)))
    return tr.t_ms, tr.truth


def _score(est: np.ndarray, truth: np.ndarray) -> tuple[float, float, float, int, int]:
    from fusion.eval.metrics import horizontal, ned_errors

    h = horizontal(ned_errors(est, truth))
    ok = np.isfinite(h)
    p50, p95 = np.percentile(h[ok], [50, 95])
    return float(p50), float(p95), float((p50 + p95) / 2), int(ok.sum()), int(np.isfinite(truth).all(1).sum())


def _ours(mode: str, out: Path, t_ms: np.ndarray, extra: list[str] = ()) -> tuple[float, np.ndarray]:
    import pandas as pd
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "1"))
    dt, _ = _timed([sys.executable, "-m", "fusion.cli", "run", str(TRACE), "--nav", str(NAV), "--mode", mode,
                    "--out", str(out), *extra], env)
    df = pd.read_csv(out / "estimates.csv")
    full = np.full((t_ms.size, 3), np.nan)
    idx = np.searchsorted(t_ms, df["gps_millis"].to_numpy(np.int64))
    ok = idx < t_ms.size
    full[idx[ok]] = df[["x_m", "y_m", "z_m"]].to_numpy(float)[ok]
    return dt, full


def _rtklib(out: Path, t_ms: np.ndarray) -> tuple[float, np.ndarray] | None:
    from fusion.geometry import geodetic2ecef
    from fusion.io.rtklib_pos import read_pos_at

    exe = shutil.which("rnx2rtkp")
    if exe is None:
        print("rnx2rtkp not found (apt-get install rtklib): RTKLIB skipped")
        return None
    pos = out / "rtk.pos"
    dt, _ = _timed([exe, "-p", "0", "-o", str(pos), str(OBS), str(NAV)])
    llh = read_pos_at(pos, t_ms)[:, :3]
    est = np.full((t_ms.size, 3), np.nan)
    ok = np.isfinite(llh).all(axis=1)
    est[ok] = geodetic2ecef(llh[ok])
    return dt, est


def _parse_time(repeats: int) -> float:
    from fusion.io.rinex_obs import read_rinex_obs

    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        read_rinex_obs(OBS)
        best = min(best, time.perf_counter() - t)
    return best


def _commands(tmp: Path, t_ms: np.ndarray, quick: bool) -> dict:
    """name -> a call timing one whole process and returning (seconds, estimates)."""
    cmds = {"RTKLIB rnx2rtkp -p 0": lambda: _rtklib(tmp, t_ms)}
    for mode in ("wls",) if quick else ("wls", "fused-nodnn", "fused"):
        cmds[f"gnssfuse run --mode {mode}"] = lambda mode=mode: _ours(mode, tmp / mode, t_ms)
    if not quick:
        # the shipped weights are an ensemble of three networks: what asking one of them would cost
        one = ["--weights", str(REPO / "learned/weights/gnssfuse_dnn_m0.pt")]
        cmds["gnssfuse run --mode fused, one network of the ensemble"] = (
            lambda: _ours("fused", tmp / "fused_one", t_ms, one))
    if not quick and (PRECISE / "COD0MGXFIN_20211180000_01D_05M_ORB.SP3").is_file():
        # multi-constellation: SP3 orbits/clocks for GPS, GLONASS, Galileo (nav: Klobuchar, TGD)
        for mode in ("wls", "fused-nodnn", "fused"):
            cmds[f"gnssfuse run --mode {mode} --sp3 --clk"] = (
                lambda mode=mode: _ours(mode, tmp / f"sp3_{mode}", t_ms, SP3_ARGS))
    return cmds


def _alternated(tmp: Path, t_ms: np.ndarray, quick: bool) -> dict:
    """Every command timed in turn, ROUNDS times over (so that a change of the machine's load hits all of
    them alike); the best time of each, with its estimates. A command that cannot run (no RTKLIB) is left out."""
    best: dict = {}
    for _ in range(1 if quick else ROUNDS):
        for name, call in _commands(tmp, t_ms, quick).items():
            got = call()
            if got is not None and (name not in best or got[0] < best[name][0]):
                best[name] = got
    return best


def compile_sources() -> None:
    """Byte-compile the package, as an installed one is: with ``PYTHONDONTWRITEBYTECODE`` set (as on this
    project's machines) every fresh process would otherwise compile its modules again (~90 ms of a run)."""
    import compileall

    for pkg in ("fusion", "learned"):
        compileall.compile_dir(str(REPO / pkg), quiet=1)


def run(quick: bool = False) -> list[dict]:
    if not OBS.is_file() or not NAV.is_file():
        print(f"shared data not found under {SHARED}: bench_pixel5 skipped")
        return []
    compile_sources()
    recs = [{"name": "RINEX obs parse (read_rinex_obs)", "value": _parse_time(1 if quick else 5),
             "unit": "s", "note": NOTE + ", best of " + ("1" if quick else "5")}]
    print(f"RINEX obs parse (read_rinex_obs, 4 MB, 1985 epochs): {recs[0]['value']:.3f} s")
    t_ms, truth = _truth()
    with tempfile.TemporaryDirectory() as tmp:
        runs = _alternated(Path(tmp), t_ms, quick)
        rtk = runs.get("RTKLIB rnx2rtkp -p 0")
    for name, (dt, est) in runs.items():
        p50, p95, score, n, n_truth = _score(est, truth)
        print(f"{name:40s} whole process {dt:6.2f} s   h p50 {p50:6.2f}  p95 {p95:6.2f}  "
              f"score {score:6.2f} m  epochs {n}/{n_truth}"
              + (f"   time vs rnx2rtkp {dt / rtk[0]:.2f}x" if rtk is not None else ""))
        recs += [{"name": f"{name} whole process", "value": dt, "unit": "s", "note": NOTE},
                 {"name": f"{name} GSDC score", "value": score, "unit": "m", "note": NOTE + f", {n}/{n_truth} epochs"},
                 {"name": f"{name} epochs solved / truth epochs", "value": n / n_truth, "unit": "", "note": NOTE}]
        if rtk is not None:
            recs.append({"name": f"{name} time / rnx2rtkp time", "value": dt / rtk[0], "unit": "x",
                         "note": NOTE + f", best of {1 if quick else ROUNDS} alternated rounds, same run"})
    return recs


if __name__ == "__main__":
    records = run(quick="--quick" in sys.argv)
    print(JSON_PREFIX + json.dumps(records))
