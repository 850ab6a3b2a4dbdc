"""Reference satellite positions and clocks from RTKLIB for the broadcast-orbit cross-check test
(tests/nav/test_rtklib_crosscheck.py), and the before/after errors of our Galileo message choice.

Regenerates, from the multi-GNSS navigation files in ../shared/data/ephemeris/gnss_lib_py_nav/:

- tests/data/rtklib_nav_records.rnx: a handful of records (GPS, Galileo I/NAV and F/NAV, BeiDou
  GEO and IGSO - the files hold no BeiDou MEO record; IGSO takes the same non-GEO path -,
  GLONASS, QZSS), one per (satellite, message), so that RTKLIB and we cannot pick different ones;
- tests/data/rtklib_sat_states.csv: RTKLIB's satellite position [m] and clock [ns] (no group
  delay) at the transmit time of a pseudorange observed at two epochs, read from the level-4
  trace of ``rnx2rtkp`` (Debian package ``rtklib``, 2.4.3 b34): its ``satposs`` prints
  ``rs`` to the millimetre and ``dts`` to the picosecond.

RTKLIB uses Galileo I/NAV records only (its default ``seleph``); the F/NAV rows come from a
second run on a copy of the records in which the F/NAV records' data-source field is set to the
I/NAV value - RTKLIB's orbit and clock maths do not depend on that field. Only RTKLIB's
outputs are stored, never its code.

    apt-get install -y rtklib
    python experiments/rtklib_sat_states.py            # rewrites the two fixture files
    python experiments/rtklib_sat_states.py --compare  # our errors against them (no RTKLIB needed)

``--compare`` prints our position / clock errors per system and, for the Galileo signal clocks
(group delay included), the errors of the message choice before this change (nearest record of
either message; E1 with the "BGD E5b/E1" field, E5a with (f1/f5)^2 times the "BGD E5a/E1" field)
and after it (E1 from I/NAV with BGD(E1,E5b), E5a from F/NAV with BGD(E1,E5a)), against RTKLIB's
clock with the group delay of the ICD pairing (RTKLIB's own E1 rule: I/NAV and BGD(E1,E5b)).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SHARED = Path(os.environ.get("GNSSFUSE_SHARED_DATA", REPO.parent / "shared" / "data"))
NAV_DIR = SHARED / "ephemeris/gnss_lib_py_nav"
OUT_NAV = REPO / "tests/data/rtklib_nav_records.rnx"
OUT_CSV = REPO / "tests/data/rtklib_sat_states.csv"
#: (file, satellite, record epoch as written, data-source value or None) of each record kept.
RECORDS = [
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "G01", "2023 03 14 02 00 00", None),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "G02", "2023 03 14 02 00 00", None),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "E01", "2023 03 14 00 40 00", 517),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "E01", "2023 03 14 00 40 00", 258),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "E02", "2023 03 14 00 20 00", 517),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "E02", "2023 03 14 00 40 00", 258),   # F/NAV only 00:30-00:50
    ("BRDM00DLR_S_20230730000_01D_MN.rnx", "C02", "2023 03 14 00 00 00", None),   # GEO (C05's is unhealthy)
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "C06", "2023 03 14 00 00 00", None),   # IGSO
    ("BRDM00DLR_S_20230730000_01D_MN.rnx", "C01", "2023 03 14 00 00 00", None),   # GEO
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "R01", "2023 03 14 00 45 00", None),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "R02", "2023 03 14 00 45 00", None),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "J02", "2023 03 14 01 00 00", None),
    ("BRDC00WRD_S_20230730000_01D_MN.rnx", "J03", "2023 03 14 01 00 00", None),
]
#: Observation epochs (GPS time) and the pseudorange written for every satellite [m]: the
#: transmit time follows from it; GEO / IGSO ranges are longer.
EPOCHS = ["2023 03 14 00 45 00.0000000", "2023 03 14 00 58 17.5000000"]
PR_M = {"G": 22_345_678.123, "R": 21_456_789.456, "E": 24_567_890.789, "J": 37_123_456.321, "C": 38_234_567.654}
#: RINEX 3 code each system's pseudorange is written under.
CODE = {"G": "C1C", "R": "C1C", "E": "C1C", "J": "C1C", "C": "C2I"}


def _record(path: Path, sat: str, epoch: str, source: int | None) -> list[str]:
    lines = path.read_text().splitlines()
    n = 4 if sat[0] == "R" else 8
    for i, ln in enumerate(lines):
        if ln.startswith(f"{sat} {epoch}"):
            rec = lines[i:i + n]
            if source is None or int(float(rec[5][23:42])) == source:
                return rec
    raise SystemExit(f"{path}: no record {sat} {epoch} source {source}")


def _header(path: Path) -> list[str]:
    keep = ("RINEX VERSION", "IONOSPHERIC CORR", "LEAP SECONDS", "TIME SYSTEM CORR")
    out = []
    for ln in path.read_text().splitlines():
        if any(k in ln[60:] for k in keep):
            out.append(ln)
        if "END OF HEADER" in ln:
            return out + [ln]
    raise SystemExit(f"{path}: no END OF HEADER")


def write_nav(path: Path, fnav_as_inav: bool | None) -> None:
    """The fixture records: all (None), or for RTKLIB the I/NAV ones (False) or the F/NAV ones
    relabelled I/NAV (True), with the other systems' records."""
    lines = _header(NAV_DIR / RECORDS[0][0])
    for f, sat, epoch, source in RECORDS:
        if source is not None and fnav_as_inav is not None and fnav_as_inav != (source == 258):
            continue
        rec = _record(NAV_DIR / f, sat, epoch, source)
        if fnav_as_inav and source == 258:
            rec[5] = rec[5][:23] + f"{517:19.12e}" + rec[5][42:]
        lines += rec
    path.write_text("\n".join(lines) + "\n")


def write_obs(path: Path) -> None:
    sats = sorted({sat for _, sat, _, _ in RECORDS}, key=lambda s: ("GRECJ".index(s[0]), s))
    head = ["     3.03           OBSERVATION DATA    M                   RINEX VERSION / TYPE",
            "".join(f"{v:14.4f}" for v in (-2.7e6, -4.3e6, 3.85e6)).ljust(60) + "APPROX POSITION XYZ"]
    for s in "GRECJ":
        head.append(f"{s}    1 {CODE[s]}".ljust(60) + "SYS / # / OBS TYPES")
    head += [" R01  1 R02 -4".ljust(60) + "GLONASS SLOT / FRQ #",
             "  2023     3    14     0    45    0.0000000     GPS         TIME OF FIRST OBS",
             " " * 60 + "END OF HEADER"]
    body = []
    for ep in EPOCHS:
        body.append(f"> {ep}  0{len(sats):3d}")
        body += [f"{s}{PR_M[s[0]]:14.3f}  " for s in sats]
    path.write_text("\n".join(head + body) + "\n")


_TRACE = re.compile(r"^4 \S+ \S+ sat=\s*(\d+) rs=\s*(\S+)\s+(\S+)\s+(\S+) dts=\s*(\S+)")
#: RTKLIB 2.4.3's satellite numbers: GPS 1-32, GLONASS 33-59, Galileo 60-95, QZSS 96-105 (PRN
#: 193-202), BeiDou 106-.
_FIRST = {"G": 1, "R": 33, "E": 60, "J": 96 - 1, "C": 106}


def rtklib_number(sat: str) -> int:
    return _FIRST[sat[0]] + int(sat[1:]) - 1 + (1 if sat[0] == "J" else 0)


def run_rtklib(nav: Path, obs: Path, work: Path) -> list[dict[int, tuple[float, ...]]]:
    """Per observation epoch: RTKLIB satellite number -> (x, y, z [m], dts [ns]) from the
    ``satposs`` lines of rnx2rtkp's level-4 trace (satellites without an ephemeris print zeros)."""
    out = work / "out.pos"
    subprocess.run(["rnx2rtkp", "-p", "0", "-sys", "G,R,E,J,C", "-x", "4", "-o", str(out), str(obs), str(nav)],
                   check=True, capture_output=True)
    epochs: list[dict[int, tuple[float, ...]]] = []
    last = None
    for ln in (work / "out.pos.trace").read_text().splitlines():
        m = _TRACE.match(ln)
        if not m:
            continue
        sat = int(m.group(1))
        if last is None or sat <= last:
            epochs.append({})
        last = sat
        vals = tuple(float(m.group(k)) for k in (2, 3, 4, 5))
        if vals[0] != 0.0:
            epochs[-1][sat] = vals
    return epochs


def main() -> int:
    sats = sorted({sat for _, sat, _, _ in RECORDS}, key=lambda s: ("GRECJ".index(s[0]), s))
    lines = ["sat,message,epoch,pr_m,x_m,y_m,z_m,dts_ns"]
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        obs = work / "obs.rnx"
        write_obs(obs)
        for message in ("inav", "fnav"):
            nav = work / f"{message}.rnx"
            write_nav(nav, fnav_as_inav=message == "fnav")
            epochs = run_rtklib(nav, obs, work)
            if len(epochs) != len(EPOCHS):
                raise SystemExit(f"rnx2rtkp trace has {len(epochs)} epochs, expected {len(EPOCHS)}")
            for ep, got in zip(EPOCHS, epochs):
                for s in sats:
                    if message == "fnav" and s[0] != "E":
                        continue
                    if rtklib_number(s) not in got:
                        print(f"RTKLIB gave no state for {s} at {ep} ({message})")
                        continue
                    x, y, z, dts = got[rtklib_number(s)]
                    msg = message if s[0] == "E" else ""
                    lines.append(f"{s},{msg},{ep},{PR_M[s[0]]:.3f},{x:.3f},{y:.3f},{z:.3f},{dts:.3f}")
    OUT_CSV.write_text("\n".join(lines) + "\n")
    write_nav(OUT_NAV, fnav_as_inav=None)
    print(f"wrote {OUT_NAV.relative_to(REPO)} and {OUT_CSV.relative_to(REPO)} ({len(lines) - 1} rows)")
    return 0


def compare() -> int:
    """Print our errors against the stored RTKLIB states (see the module docstring)."""
    import pandas as pd

    from fusion.geometry import C_LIGHT
    from fusion.io.rinex_nav import GAMMA_L5, read_nav
    from fusion.nav.orbits import sat_state, select_ephemeris
    from fusion.nav.sat_states import group_delay, select_record
    from fusion.trace import SIGNALS

    sys.path.insert(0, str(REPO / "tests"))
    from test_rtklib_crosscheck import _ours, _transmit_offset  # noqa: E402 (the test's own arithmetic)

    nav = read_nav(OUT_NAV)
    ref = pd.read_csv(OUT_CSV, keep_default_na=False)
    from fusion.gpstime import gps_ms_from_calendar
    ref["t_ms"] = [gps_ms_from_calendar(*(int(v) for v in p[:5]), float(p[5])) for p in ref.epoch.str.split()]
    ctype = {"G": 1, "R": 3, "J": 4, "C": 5, "E": 6}
    ref["sat_id"] = [ctype[s[0]] * 1000 + int(s[1:]) + (192 if s[0] == "J" else 0) for s in ref.sat]
    print("| system | rows | max position error [mm] | max clock error [mm] |\n|---|---|---|---|")
    for system in "GRECJ":
        rows = ref[ref.sat.str[0] == system]
        pos, clock = _ours(nav, rows)
        e_pos = np.linalg.norm(pos - rows[["x_m", "y_m", "z_m"]].to_numpy(), axis=1).max() * 1e3
        e_clk = np.abs(clock - rows.dts_ns.to_numpy() * 1e-9).max() * C_LIGHT * 1e3
        print(f"| {system} | {len(rows)} | {e_pos:.2f} | {e_clk:.2f} |")
    k = nav.kepler
    print("\n| satellite | epoch | signal | before: error [m] | after: error [m] |\n|---|---|---|---|---|")
    gal = ref[ref.sat.str[0] == "E"]
    for (sat, ep), grp in gal.groupby(["sat", "epoch"], sort=False):
        r = grp.set_index("message")
        t_ms, sat_id, flight = int(r.t_ms.iloc[0]), int(r.sat_id.iloc[0]), float(r.pr_m.iloc[0]) / C_LIGHT
        rec = {m: select_ephemeris(k, [sat_id], [t_ms], by_sat_id=True, msg=[i])[0] for i, m in enumerate(("inav", "fnav"))}
        # the signal clocks of the ICD pairings: E1 = I/NAV - BGD(E1,E5b) (RTKLIB's E1 rule) or
        # F/NAV - BGD(E1,E5a); E5a = F/NAV - (f1/f5)^2 BGD(E1,E5a)
        truth = {"GAL_E1": r.dts_ns["inav"] * 1e-9 - k.params["iodc"][rec["inav"]],
                 "GAL_E1 (F/NAV pairing)": r.dts_ns["fnav"] * 1e-9 - k.params["tgd"][rec["fnav"]],
                 "GAL_E5A": r.dts_ns["fnav"] * 1e-9 - k.params["tgd_l5"][rec["fnav"]]}
        for label in truth:
            name = label.split()[0]
            sig = np.array([SIGNALS.index(name)])
            near = min(rec.values(), key=lambda i: (abs(int(k.toe_ms[i]) - t_ms), int(k.msg[i])))
            old_gd = k.params["iodc"][near] if name == "GAL_E1" else GAMMA_L5 * _bgd_a(k, near)
            new = select_record(k, np.array([sat_id]), sig, np.array([t_ms]))[0]
            out = []
            for i, gd in ((near, old_gd), (new, group_delay(k, np.array([new]), sig)[0])):
                p = {n: v[i] for n, v in k.params.items()}
                ts = (t_ms - k.toc_ms[i]) * 1e-3 - flight
                dt = -flight - _transmit_offset(lambda t: p["af0"] + p["af1"] * t + p["af2"] * t * t, np.array([ts]))
                clk = sat_state(k, np.array([i]), np.array([t_ms]), dt)["clock_s"][0] + p["tgd"] - gd
                out.append((clk - truth[name]) * C_LIGHT)
            out = [o + truth[name] * C_LIGHT - truth[label] * C_LIGHT for o in out]
            print(f"| {sat} | {ep[11:19]} | {label} | {out[0]:+.3f} | {out[1]:+.3f} |")
    return 0


def _bgd_a(k, i: int) -> float:
    """The record's "BGD E5a/E1" field (the F/NAV E1 group delay is that field)."""
    return float(k.params["tgd"][i]) if k.msg[i] == 1 else float(
        (k.params["tgd_l5"][i] - k.params["tgd"][i]) / (((1575.42 / 1176.45) ** 2) - 1))


if __name__ == "__main__":
    sys.exit(compare() if "--compare" in sys.argv else main())
