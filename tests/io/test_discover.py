"""Navigation and observation files found by their header (any name, gzip, Hatanaka), the one
plain-or-gzip reader, and what the loader says about the navigation it used."""
from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest

from fusion.errors import DataError
from fusion.io.discover import files_of_kind, is_gnss_logger, rinex_kind
from fusion.prepare.load import load_trace
from fusion.prepare.raw_load import navigation_files, raw_log_files
from fusion.io.rinex_nav import default_nav_path, read_nav
from fusion.io.rinex_obs import read_rinex_obs
from fusion.io.sp3 import read_sp3
from fusion.io.text_open import read_bytes

DATA = Path(__file__).resolve().parents[1] / "data"
MIXED = DATA / "brdc_2023073_mixed_305.rnx"
P5_HEAD = DATA / "pixel5_head.21o"


def _beidou_only(path: Path) -> Path:
    """A RINEX 3.02 BeiDou navigation file with a RINEX-2-style name, as Hong Kong's service
    publishes it (``hksc137c.21f``): the BeiDou records of the mixed fixture."""
    lines = MIXED.read_text().splitlines()
    body = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    recs = [ln for i, ln in enumerate(lines[body:]) if _owner(lines[body:], i) == "C"]
    head = ["     3.02           N: GNSS NAV DATA    C: BDS              RINEX VERSION / TYPE",
            " " * 60 + "END OF HEADER"]
    path.write_text("\n".join(head + recs) + "\n")
    return path


def _owner(lines: list[str], i: int) -> str:
    """The system letter of the record line ``i`` belongs to."""
    while lines[i][:1] == " ":
        i -= 1
    return lines[i][0]


def test_kinds_by_content(tmp_path):
    f = _beidou_only(tmp_path / "hksc137c.21f")
    assert rinex_kind(f) == rinex_kind(f).__class__("nav", "C", 3.02)
    assert rinex_kind(MIXED).kind == "nav" and rinex_kind(MIXED).system == "M"
    g = tmp_path / "renamed.dat.gz"
    g.write_bytes(gzip.compress(default_nav_path().read_bytes()))
    assert (rinex_kind(g).kind, rinex_kind(g).system) == ("nav", "G")      # RINEX 2 GPS, gzipped
    assert rinex_kind(P5_HEAD).kind == "obs"
    v4 = tmp_path / "BRD400DLR_S_20230730000_01D_MN.rnx"
    v4.write_text("     4.01           N: GNSS NAV DATA    M: MIXED            RINEX VERSION / TYPE\n")
    assert rinex_kind(v4) == rinex_kind(v4).__class__("nav", "M", 4.01)                # RINEX 4, the IGS merge
    (tmp_path / "notes.txt").write_text("hello\n")
    assert rinex_kind(tmp_path / "notes.txt") is None and rinex_kind(tmp_path / "absent") is None


def test_gnss_logger_logs_found_by_content(tmp_path):
    """A GnssLogger log renamed by whoever shared it (gnss_lib_py ships one as ``pixel6.txt``), plain or
    gzipped, is a raw log of the folder; a derived CSV or a note named .txt is not. Read as a GnssLogger
    log, not as the GSDC 2021 derived file its .txt name would otherwise suggest."""
    log = DATA / "pixel4_gnss_log.txt"
    (tmp_path / "supplemental").mkdir()
    shutil.copy(log, tmp_path / "pixel6.txt")
    (tmp_path / "supplemental" / "drive.txt.gz").write_bytes(gzip.compress(log.read_bytes()))
    (tmp_path / "notes.txt").write_text("Raw data of the drive, see the app\n")
    assert is_gnss_logger(tmp_path / "pixel6.txt") and is_gnss_logger(tmp_path / "supplemental" / "drive.txt.gz")
    assert not is_gnss_logger(tmp_path / "notes.txt") and not is_gnss_logger(tmp_path / "absent.txt")
    assert sorted(p.name for p in raw_log_files(tmp_path)) == ["drive.txt.gz", "pixel6.txt"]
    from fusion.prepare.raw_load import read_raw
    assert len(read_raw(tmp_path / "pixel6.txt").frame) > 0


def test_folder_navigation_of_every_name(tmp_path, capsys):
    """The GPS .21n and the BeiDou .21f of one folder are both read (the .21f was ignored before)."""
    shutil.copy(default_nav_path(), tmp_path / "hksc137c.21n")
    _beidou_only(tmp_path / "hksc137c.21f")
    sbas = tmp_path / "S.rnx"
    sbas.write_text("     3.04           N: GNSS NAV DATA    S: SBAS             RINEX VERSION / TYPE\n")
    files = navigation_files(tmp_path)
    assert [p.name for p in files] == ["hksc137c.21f", "hksc137c.21n"]
    assert "S.rnx holds SBAS records only: not used" in capsys.readouterr().err
    nav = read_nav(files)
    assert nav.systems() == {"G", "C"}
    assert {Path(k).name: v for k, v in nav.file_systems.items()} == {"hksc137c.21f": {"C"}, "hksc137c.21n": {"G"}}


def test_hatanaka_observations_read_like_plain(tmp_path):
    hatanaka = pytest.importorskip("hatanaka")
    crx = tmp_path / "site1180.21d.gz"
    crx.write_bytes(gzip.compress(hatanaka.rnx2crx(P5_HEAD.read_bytes())))
    assert rinex_kind(crx).kind == "obs" and rinex_kind(crx).hatanaka
    a, b = read_rinex_obs(P5_HEAD).frame, read_rinex_obs(crx).frame
    assert len(a) == len(b) > 0
    np.testing.assert_array_equal(a.pr_m.to_numpy(), b.pr_m.to_numpy())
    np.testing.assert_array_equal(a.adr_m.to_numpy(), b.adr_m.to_numpy())
    bad = tmp_path / "bad.crx"
    bad.write_bytes(b"1.0                 COMPACT RINEX FORMAT                    CRINEX VERS   / TYPE\ngarbage\n")
    with pytest.raises(DataError, match="bad.crx: cannot expand Hatanaka"):
        read_rinex_obs(bad)


def test_loader_finds_files_by_content_and_says_what_it_used(tmp_path, capsys):
    pytest.importorskip("hatanaka")
    import hatanaka
    folder = tmp_path / "drive" / "phone"
    (folder / "supplemental").mkdir(parents=True)
    (folder / "supplemental" / "log.crx").write_bytes(hatanaka.rnx2crx(P5_HEAD.read_bytes()))
    shutil.copy(default_nav_path(), folder / "broadcast.nav.txt")
    assert raw_log_files(folder) == [folder / "supplemental" / "log.crx"]
    assert files_of_kind(folder, "nav") == [folder / "broadcast.nav.txt"]
    with pytest.warns(UserWarning, match="no navigation for Galileo"):
        tr = load_trace(folder, signals=None, min_sats=1)
    assert tr.n_epochs == 5
    assert "navigation: broadcast.nav.txt (GPS, records 2021-04-28 00:00 to 2021-04-28 23:59 GPST)" in capsys.readouterr().err


def test_one_reader_for_plain_and_gzip(tmp_path):
    plain = tmp_path / "a.txt"
    plain.write_bytes(b"abc\n")
    gz = tmp_path / "a.bin"                       # gzip told by content, not name
    gz.write_bytes(gzip.compress(b"abc\n"))
    assert read_bytes(plain, "x") == read_bytes(gz, "x") == b"abc\n"
    fake = tmp_path / "b.gz"
    fake.write_bytes(b"abc")
    with pytest.raises(DataError, match="b.gz: corrupt gzip x file"):
        read_bytes(fake, "x")
    with pytest.raises(DataError, match="c: x file not found"):
        read_bytes(tmp_path / "c", "x")
    with pytest.raises(DataError, match="a folder, not a x file"):
        read_bytes(tmp_path, "x")
    with pytest.raises(DataError, match="not a regular file"):
        read_bytes(Path("/dev/null"), "x")


SP3 = """#dP2021  4 28  0  0  0.00000000       2 ORBIT IGS14 HLM  IGS
%c M  cc GPS ccc cccc cccc cccc cccc ccccc ccccc ccccc ccccc
*  2021  4 28  0  0  0.00000000
PG01  -1000.000000  20000.000000  15000.000000     12.500000
*  2021  4 28  0  5  0.00000000
PG01  -1100.000000  20100.000000  14900.000000     12.600000
PG01  -1100.000000  20100.000000  14900.000000     12.600000
EOF
"""


def test_sp3_gz_is_read(tmp_path):
    """read_sp3 decompresses .sp3.gz (it accepted the name before but read the bytes as text)."""
    plain = tmp_path / "x.sp3"
    plain.write_text(SP3)
    gz = tmp_path / "x.sp3.gz"
    gz.write_bytes(gzip.compress(SP3.encode()))
    a, b = read_sp3(plain), read_sp3(gz)
    np.testing.assert_array_equal(a.pos, b.pos)
    assert a.pos[1, 0, 0] == -1_100_000.0 and b.clock[0, 0] == pytest.approx(12.5e-6)


def test_glonass_channels_from_navigation_records():
    """The loader hands these to the observation reader for slots its header lacks; they agree
    with the slot table here."""
    from fusion.io.nav_records import SLOT_CHANNEL
    ch = read_nav(MIXED).glonass_channels()
    assert ch == {1: SLOT_CHANNEL[1], 2: SLOT_CHANNEL[2]}


def test_navigation_span(tmp_path):
    nav = read_nav(MIXED)
    lo, hi = nav.span_ms()
    from fusion.gpstime import format_gps_ms
    assert format_gps_ms(lo)[:10] == "2023-03-13" and format_gps_ms(hi)[:10] == "2023-03-14"
