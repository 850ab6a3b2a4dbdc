"""``gnssfuse run --export gpx,kml,nmea,pos``: every format read back (gpxpy, the KML XML, our NMEA
reader and an independent checksum, the .pos columns and RTKLIB's own pos2kml where installed)."""
from __future__ import annotations

import shutil
import subprocess
import xml.etree.ElementTree as ET
from datetime import timezone
from pathlib import Path

import gpxpy
import numpy as np
import pandas as pd
import pytest

from fusion.cli import main
from fusion.errors import GnssfuseError
from fusion.geometry import geodetic2ecef, ned2ecef_cov
from fusion.gpstime import gps_ms_to_unix_ms
from fusion.io.estimates import export_frame
from fusion.io.export import WRITERS, parse_formats, write_exports
from fusion.io.nmea import read_span_nmea
from fusion.io.nmea_write import checksum
from fusion.run_types import ModeResult
from fusion.trace import Trace, empty_trace

KML = "{http://www.opengis.net/kml/2.2}"
#: (lat, lon) start points in every hemisphere, one just below a whole minute of latitude (rounding
#: must carry into the degrees, not print 60 minutes)
STARTS = [(37.4, -122.1), (-33.86, 151.2), (59.99999999999, 10.75), (-0.5, -0.25)]


def _trace_and_result(lat0: float, lon0: float, E: int = 40, with_cov: bool = True):
    kw = empty_trace(E, 6, name="synthetic/Phone")
    kw["t_ms"] = 1_303_669_148_433 + 1000 * np.arange(E, dtype=np.int64)      # 2021-04-28, GPS ms
    kw["mask"][:, :5] = True
    kw["mask"][::3, 5] = True                                                  # 5 or 6 satellites
    llh = np.c_[lat0 + 1e-5 * np.arange(E), lon0 - 2e-5 * np.arange(E), 10.0 + 0.1 * np.arange(E)]
    pos = geodetic2ecef(llh)
    valid = np.ones(E, bool)
    valid[4] = False                                                           # one unsolved epoch
    pos[4] = np.nan
    cov = None
    if with_cov:
        rng = np.random.default_rng(0)
        a = rng.normal(size=(E, 3, 3))
        ned = a @ np.swapaxes(a, 1, 2) + np.eye(3)                             # SPD, correlated
        cov = ned2ecef_cov(ned, np.where(valid[:, None], pos, geodetic2ecef(llh)))
    return Trace(**kw), ModeResult(pos=pos, valid=valid, cov=cov), llh


@pytest.fixture(params=STARTS, ids=lambda s: f"{s[0]:+.0f},{s[1]:+.0f}")
def exported(request, tmp_path):
    trace, result, llh = _trace_and_result(*request.param)
    frame = export_frame(trace, result)
    paths = write_exports(frame, tmp_path, tuple(WRITERS), "synthetic (wls)")
    return frame, {p.suffix[1:]: p for p in paths}, trace


def test_frame_has_one_row_per_solved_epoch(exported):
    frame, _, trace = exported
    assert len(frame) == trace.n_epochs - 1
    assert (frame["n_sats"].to_numpy() == trace.mask.sum(1)[np.r_[0:4, 5:trace.n_epochs]]).all()


def test_gpx_reads_back_with_gpxpy(exported):
    frame, paths, _ = exported
    gpx = gpxpy.parse(paths["gpx"].read_text())
    pts = [p for t in gpx.tracks for s in t.segments for p in s.points]
    assert len(pts) == len(frame)
    np.testing.assert_allclose([p.latitude for p in pts], frame.lat_deg, atol=1e-9)
    np.testing.assert_allclose([p.longitude for p in pts], frame.lon_deg, atol=1e-9)
    np.testing.assert_allclose([p.elevation for p in pts], frame.height_m, atol=1e-6)
    unix_ms = [round(p.time.astimezone(timezone.utc).timestamp() * 1000) for p in pts]
    assert unix_ms == gps_ms_to_unix_ms(frame.gps_millis.to_numpy()).tolist()    # UTC: 18 s before GPS
    assert "ellipsoidal" in gpx.description


def test_kml_line_and_placemarks_with_sigma(exported):
    frame, paths, _ = exported
    doc = ET.parse(paths["kml"]).getroot().find(f"{KML}Document")
    line = doc.find(f"{KML}Placemark/{KML}LineString/{KML}coordinates").text.split()
    lon, lat, h = np.array([c.split(",") for c in line], float).T
    np.testing.assert_allclose(lat, frame.lat_deg, atol=1e-8)
    np.testing.assert_allclose(lon, frame.lon_deg, atol=1e-8)
    np.testing.assert_allclose(h, frame.height_m, atol=1e-3)
    marks = doc.findall(f"{KML}Folder/{KML}Placemark")
    assert len(marks) == len(frame)
    sigma = [float(m.find(f"{KML}description").text.split("error ")[1].split(" m")[0]) for m in marks]
    np.testing.assert_allclose(sigma, np.hypot(frame.sigma_n_m, frame.sigma_e_m), atol=0.006)
    assert marks[0].find(f"{KML}TimeStamp/{KML}when").text.endswith("Z")


def test_kml_without_covariance_has_no_sigma(tmp_path):
    trace, result, _ = _trace_and_result(37.4, -122.1, with_cov=False)
    (path,) = write_exports(export_frame(trace, result), tmp_path, ("kml",), "x")
    assert "1-sigma" not in path.read_text() and path.read_text().count("<Placemark>") == trace.n_epochs


def test_nmea_checksums_and_positions(exported):
    frame, paths, trace = exported
    raw = paths["nmea"].read_bytes()
    assert raw.count(b"\r\n") == 2 * len(frame)                 # NMEA 0183 line ends
    lines = raw.decode("ascii").split("\r\n")[:-1]
    for ln in lines:                                            # XOR of the body, written independently here
        body, _, cs = ln[1:].partition("*")
        x = 0
        for ch in body.encode():
            x ^= ch
        assert ln[0] == "$" and len(ln) <= 82 and cs == f"{x:02X}", ln
    assert [ln[3:6] for ln in lines] == ["GGA", "RMC"] * len(frame)
    skipped: dict[str, int] = {}
    back = read_span_nmea(paths["nmea"], skipped=skipped)       # our SPAN reader: GGA + RMC date
    assert not skipped
    assert back.t_ms.tolist() == frame.gps_millis.tolist()
    np.testing.assert_allclose(back.lat_deg, frame.lat_deg, atol=2e-9)     # 1e-7 minutes
    np.testing.assert_allclose(back.lon_deg, frame.lon_deg, atol=2e-9)
    np.testing.assert_allclose(back.height_m, frame.height_m, atol=1e-3)   # altitude + separation
    assert back.n_sats.tolist() == frame.n_sats.tolist()


def test_checksum_of_a_published_sentence():
    # a GGA sentence with its checksum as a receiver wrote it (NMEA 0183 examples)
    assert checksum("GPGGA,092750.000,5321.6802,N,00630.3372,W,1,8,1.03,61.7,M,55.2,M,,") == "76"


def _read_pos(path: Path) -> pd.DataFrame:
    names = ["week", "tow", "lat", "lon", "h", "Q", "ns", "sdn", "sde", "sdu", "sdne", "sdeu", "sdun", "age", "ratio"]
    return pd.read_csv(path, sep=r"\s+", comment="%", header=None, names=names)


def test_pos_columns(exported):
    frame, paths, _ = exported
    text = paths["pos"].read_text()
    assert "WGS84/ellipsoidal" in text
    pos = _read_pos(paths["pos"])
    assert len(pos) == len(frame) and (pos.Q == 5).all()
    t = pos.week.to_numpy() * 604_800_000 + np.round(pos.tow.to_numpy() * 1000).astype(np.int64)
    assert t.tolist() == frame.gps_millis.tolist()
    np.testing.assert_allclose(pos.lat, frame.lat_deg, atol=1e-9)
    np.testing.assert_allclose(pos.lon, frame.lon_deg, atol=1e-9)
    np.testing.assert_allclose(pos.h, frame.height_m, atol=1e-4)
    assert pos.ns.tolist() == frame.n_sats.tolist()
    np.testing.assert_allclose(pos[["sdn", "sde", "sdu"]], frame[["sigma_n_m", "sigma_e_m", "sigma_d_m"]], atol=1e-4)
    # RTKLIB: sdne = sign(Qne) sqrt|Qne|, in east-north-UP (so EU and UN flip sign from NED)
    q_ne, q_ed = frame.cov_ne_m2.to_numpy(), frame.cov_ed_m2.to_numpy()
    np.testing.assert_allclose(pos.sdne, np.sign(q_ne) * np.sqrt(np.abs(q_ne)), atol=1e-4)
    np.testing.assert_allclose(pos.sdeu, -np.sign(q_ed) * np.sqrt(np.abs(q_ed)), atol=1e-4)


@pytest.mark.skipif(shutil.which("pos2kml") is None, reason="RTKLIB's pos2kml is not installed")
def test_rtklib_reads_our_pos(exported, tmp_path):
    frame, paths, _ = exported
    out = tmp_path / "rtklib.kml"
    subprocess.run(["pos2kml", "-a", "-o", str(out), str(paths["pos"])], capture_output=True, check=True)
    points = np.array([c.text.strip().split(",") for c in ET.parse(out).getroot().iter()
                       if c.tag.endswith("}coordinates") and len(c.text.split()) == 1], float)  # per-epoch points
    assert len(points) == len(frame)
    np.testing.assert_allclose(points[:, 1], frame.lat_deg, atol=1e-8)
    np.testing.assert_allclose(points[:, 0], frame.lon_deg, atol=1e-8)


def test_parse_formats():
    assert parse_formats("gpx, KML,gpx") == ("gpx", "kml")
    with pytest.raises(GnssfuseError, match="--export"):
        parse_formats("gpx,shp")


def test_run_export_on_the_shipped_trace(shipped_trace_dir, tmp_path, capsys):
    if not shipped_trace_dir.is_dir():
        pytest.skip("shipped trace missing")
    out = tmp_path / "out"
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--out", str(out), "--export", "gpx,kml,nmea,pos"]) == 0
    est = pd.read_csv(out / "estimates.csv")
    for fmt in WRITERS:
        assert (out / f"estimates.{fmt}").stat().st_size > 0
    assert len(_read_pos(out / "estimates.pos")) == len(est)
    assert len(read_span_nmea(out / "estimates.nmea")) == len(est)
    assert sum(len(s.points) for t in gpxpy.parse((out / "estimates.gpx").read_text()).tracks for s in t.segments) == len(est)
    assert "ellipsoidal" in capsys.readouterr().out


def test_export_given_twice_writes_both(shipped_trace_dir, tmp_path):
    out = tmp_path / "twice"
    assert main(["run", str(shipped_trace_dir), "--mode", "wls", "--out", str(out), "--export", "gpx",
                 "--export", "pos"]) == 0
    assert (out / "estimates.gpx").is_file() and (out / "estimates.pos").is_file()


def test_run_export_unknown_format_is_one_line(shipped_trace_dir, tmp_path, capsys):
    assert main(["run", str(shipped_trace_dir), "--out", str(tmp_path / "o"), "--export", "shp"]) == 2
    err = capsys.readouterr().err
    assert "--export" in err and err.strip().count("\n") == 0


def test_nmea_rmc_speed_and_course(exported):
    """RMC's speed [knots] and course [deg true] match the synthetic track's motion: 1e-5 deg of latitude
    and -2e-5 deg of longitude per second (north-west); the epoch after the unsolved one differences
    across the 2 s gap, and every field is filled (the track moves faster than MIN_COURSE_MPS)."""
    frame, paths, _ = exported
    rmc = [ln.split("*")[0].split(",") for ln in paths["nmea"].read_text().splitlines() if ln[3:6] == "RMC"]
    lat0 = np.radians(frame.lat_deg.iloc[0])
    north = np.radians(1e-5) * 6_371_000.0                      # m/s, a sphere: 0.5 % is enough
    east = -np.radians(2e-5) * 6_371_000.0 * np.cos(lat0)
    speed_kn = np.array([float(f[7]) for f in rmc])
    course = np.array([float(f[8]) for f in rmc])
    np.testing.assert_allclose(speed_kn, np.hypot(north, east) * 3600 / 1852, rtol=5e-3)
    expect = np.degrees(np.arctan2(east, north)) % 360
    assert np.all(np.abs((course - expect + 180) % 360 - 180) < 0.5)


def test_nmea_rmc_leaves_speed_empty_across_a_gap(tmp_path):
    from fusion.io.nmea_write import MAX_SPEED_GAP_S, nmea_lines

    frame = pd.DataFrame({"gps_millis": [0, 1000, 1000 + int(1000 * (MAX_SPEED_GAP_S + 5))],
                          "lat_deg": [37.4, 37.40001, 37.5], "lon_deg": [-122.1] * 3, "height_m": [10.0] * 3})
    rmc = [ln.split("*")[0].split(",") for ln in nmea_lines(frame) if ln[3:6] == "RMC"]
    assert rmc[0][7] and rmc[1][7] and rmc[2][7] == "" and rmc[2][8] == ""    # the lone last fix: no speed
    still = frame.assign(lat_deg=37.4)
    assert [f.split("*")[0].split(",")[8] for f in nmea_lines(still) if f[3:6] == "RMC"] == ["", "", ""]


def test_graph_velocity_becomes_ned_columns_and_rmc_speed():
    """A graph mode's velocity states (info["vel"], ECEF) and their marginals (info["vel_cov"]) are written
    north/east/down at the estimate where Doppler measures them, and RMC takes its speed and course from them
    rather than from the track (which here stands still); without Doppler anywhere there are no velocity
    columns."""
    from fusion.geometry import ned2ecef_vec
    from fusion.io.estimates import VELOCITY_COLUMNS, VELOCITY_SIGMA_COLUMNS, estimates_frame
    from fusion.io.nmea_write import KNOTS_PER_MPS, nmea_lines

    trace, result, llh = _trace_and_result(37.4, -122.1, E=6)
    still = np.where(result.valid[:, None], geodetic2ecef(np.repeat(llh[:1], 6, axis=0)), np.nan)
    want = np.array([3.0, -4.0, 0.5])                                    # m/s north, east, down
    vel = ned2ecef_vec(np.tile(want, (6, 1)), geodetic2ecef(llh[:1]).repeat(6, axis=0))
    doppler = np.ones(6, bool)
    doppler[2] = False                                                   # an epoch without a Doppler factor
    vel_cov = ned2ecef_cov(np.tile(np.diag([0.01, 0.04, 0.09]), (6, 1, 1)), geodetic2ecef(llh[:1]).repeat(6, axis=0))
    info = {"vel": vel, "doppler_epochs": doppler, "vel_cov": vel_cov}
    result = ModeResult(pos=still, valid=result.valid, cov=None, info=info)
    frame = estimates_frame(trace, result)
    assert list(frame.columns[-6:]) == VELOCITY_COLUMNS + VELOCITY_SIGMA_COLUMNS
    got, sig = frame[VELOCITY_COLUMNS].to_numpy(), frame[VELOCITY_SIGMA_COLUMNS].to_numpy()
    np.testing.assert_allclose(np.delete(got, 2, axis=0), np.tile(want, (4, 1)), atol=1e-9)
    np.testing.assert_allclose(np.delete(sig, 2, axis=0), np.tile([0.1, 0.2, 0.3], (4, 1)), atol=1e-9)
    assert np.isnan(got[2]).all() and np.isnan(sig[2]).all()
    rmc = [ln.split("*")[0].split(",") for ln in nmea_lines(frame) if ln[3:6] == "RMC"]
    speeds = [f[7] for f in rmc]
    assert float(speeds[0]) == pytest.approx(5.0 * KNOTS_PER_MPS, abs=1e-3)
    assert float(rmc[0][8]) == pytest.approx(np.degrees(np.arctan2(-4.0, 3.0)) % 360, abs=0.01)
    assert float(speeds[2]) == pytest.approx(0.0, abs=1e-3)              # no Doppler: the (still) track's speed
    none = ModeResult(pos=still, valid=result.valid, cov=None, info={"vel": vel, "doppler_epochs": np.zeros(6, bool)})
    assert "vel_n_mps" not in estimates_frame(trace, none)
    no_cov = ModeResult(pos=still, valid=result.valid, cov=None, info={"vel": vel, "doppler_epochs": doppler})
    assert list(estimates_frame(trace, no_cov).columns[-3:]) == VELOCITY_COLUMNS     # no marginals (a band too wide)


def test_pos_velocity_columns_as_rnx2rtkp_writes_them(tmp_path):
    """With the graph's velocity, the .pos lines carry rnx2rtkp's ``out-outvel`` columns: vn, ve, vu (up =
    -down), their sigmas and the signed square roots of the NE / EU / UN covariances; an epoch without Doppler
    gets zeros (RTKLIB's unknown), and RTKLIB's pos2kml still reads the file where installed."""
    from fusion.geometry import ned2ecef_vec
    from fusion.io.rtklib_pos import VELOCITY_HEADER

    trace, result, llh = _trace_and_result(-33.86, 151.2, E=6)
    at = geodetic2ecef(llh)
    want = np.array([3.0, -4.0, 0.5])                                    # m/s north, east, down
    vel_ned_cov = np.array([[0.04, 0.01, -0.02], [0.01, 0.09, 0.03], [-0.02, 0.03, 0.16]])
    doppler = np.ones(6, bool)
    doppler[2] = False
    info = {"vel": ned2ecef_vec(np.tile(want, (6, 1)), at), "doppler_epochs": doppler,
            "vel_cov": ned2ecef_cov(np.tile(vel_ned_cov, (6, 1, 1)), at)}
    frame = export_frame(trace, ModeResult(pos=result.pos, valid=result.valid, cov=result.cov, info=info))
    path = write_exports(frame, tmp_path, ("pos",), "synthetic (fused)")[0]
    assert VELOCITY_HEADER in path.read_text()
    names = ["week", "tow", "lat", "lon", "h", "Q", "ns", "sdn", "sde", "sdu", "sdne", "sdeu", "sdun", "age", "ratio",
             "vn", "ve", "vu", "sdvn", "sdve", "sdvu", "sdvne", "sdveu", "sdvun"]
    pos = pd.read_csv(path, sep=r"\s+", comment="%", header=None, names=names)
    assert len(pos) == 5                                                 # epoch 4 unsolved
    measured = pos.drop(index=2)                                         # epoch 2: no Doppler
    np.testing.assert_allclose(measured[["vn", "ve", "vu"]], np.tile([3.0, -4.0, -0.5], (4, 1)), atol=1e-5)
    np.testing.assert_allclose(measured[["sdvn", "sdve", "sdvu"]], np.tile([0.2, 0.3, 0.4], (4, 1)), atol=1e-5)
    # ENU cross terms: NE as is, EU = -ED, UN = -ND, each sign(q) sqrt|q|
    np.testing.assert_allclose(measured[["sdvne", "sdveu", "sdvun"]], np.tile([0.1, -np.sqrt(0.03), np.sqrt(0.02)],
                                                                              (4, 1)), atol=1e-5)
    assert (pos.loc[2, names[15:]] == 0).all()
    np.testing.assert_allclose(pos[["sdn", "sde", "sdu"]], frame[["sigma_n_m", "sigma_e_m", "sigma_d_m"]], atol=1e-4)
    if shutil.which("pos2kml"):
        out = tmp_path / "rtklib.kml"
        subprocess.run(["pos2kml", "-a", "-o", str(out), str(path)], capture_output=True, check=True)
        assert sum(c.tag.endswith("}coordinates") and len(c.text.split()) == 1
                   for c in ET.parse(out).getroot().iter()) == 5


def test_epochs_the_motion_model_carried_are_marked_dead_reckoning(tmp_path):
    """The graph's bridged epochs (fewer than four satellites, no prior) are GGA quality 6 and RMC mode E
    (estimated) in NMEA, and Q = 7 (RTKLIB's dead reckoning) in the .pos file; the others 1 / A and 5."""
    trace, result, _ = _trace_and_result(37.4, -122.1, E=8)
    bridged = np.zeros(8, bool)
    bridged[[2, 3]] = True
    frame = export_frame(trace, ModeResult(pos=result.pos, valid=result.valid, cov=result.cov,
                                           info={"bridged": bridged}))
    paths = {p.suffix[1:]: p for p in write_exports(frame, tmp_path, ("nmea", "pos"), "synthetic (fused)")}
    lines = paths["nmea"].read_text().splitlines()
    gga = [ln.split(",")[6] for ln in lines if ln[3:6] == "GGA"]
    rmc = [ln.split("*")[0].split(",")[-1] for ln in lines if ln[3:6] == "RMC"]
    # epoch 4 is unsolved: seven rows
    assert gga == ["1", "1", "6", "6", "1", "1", "1"] and rmc == ["A", "A", "E", "E", "A", "A", "A"]
    assert _read_pos(paths["pos"]).Q.tolist() == [5, 5, 7, 7, 5, 5, 5]


def test_a_pos_file_is_read_back_at_the_epochs(exported):
    """fusion.io.rtklib_pos.read_pos_at (what the RTKLIB comparisons read rnx2rtkp's output with): each solved
    epoch's line by its time, NaN where no line is (the unsolved epoch 4)."""
    from fusion.io.rtklib_pos import read_pos_at

    frame, paths, trace = exported
    got = read_pos_at(paths["pos"], trace.t_ms)
    assert np.isnan(got[4]).all() and np.isfinite(np.delete(got, 4, axis=0)).all()
    np.testing.assert_allclose(np.delete(got, 4, axis=0)[:, :3], frame[["lat_deg", "lon_deg", "height_m"]],
                               atol=1e-4)
