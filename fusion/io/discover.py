"""Tell measurement and navigation files apart by what they hold, not by their names.

A RINEX file says what it is in its first line (``RINEX VERSION / TYPE``): version, file type
(``N`` navigation, ``G`` GLONASS navigation in RINEX 2, ``O`` observation, ...) and, for RINEX 3,
the satellite system (``G R E C J I S``, ``M`` mixed). A Hong Kong reference-station BeiDou file
``hksc137c.21f`` is a RINEX 3.02 ``N`` / ``C`` file with a RINEX-2-style name; an IGS
``*_EN.rnx`` is Galileo; both are navigation whatever their extension. Hatanaka-compressed
observations start with ``COMPACT RINEX FORMAT`` and carry the RINEX header two lines later.
Gzip is looked through (:func:`fusion.io.text_open.head_text`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from fusion.io.text_open import head_text

#: RINEX 2 navigation file types -> the system they hold (``N`` GPS, ``G`` GLONASS, ``H`` SBAS,
#: ``L`` / ``E`` Galileo in some 2.1x writers, ``J`` / ``Q`` QZSS). A RINEX 2 type ``C`` is a clock file;
#: BeiDou navigation comes as RINEX 3 (whatever the file's name, e.g. Hong Kong's ``.21f``).
_V2_NAV = {"N": "G", "G": "R", "H": "S", "L": "E", "E": "E", "J": "J", "Q": "J"}
#: System letter -> constellation name for messages.
SYSTEM_NAMES = {"G": "GPS", "R": "GLONASS", "E": "Galileo", "C": "BeiDou", "J": "QZSS", "I": "NavIC",
                "S": "SBAS", "M": "mixed"}
#: Names never sniffed: tables, logs and outputs that cannot be RINEX.
_TABLE_SUFFIXES = (".csv", ".csv.gz", ".nmea", ".nmea.gz", ".json", ".png", ".md", ".pt")


@dataclass(frozen=True)
class RinexKind:
    """What a file's first header line says. kind: ``nav`` / ``obs`` / ``clock`` / ``other``;
    system: the RINEX system letter (``M`` mixed); version: e.g. 3.04; hatanaka: CRINEX."""

    kind: str
    system: str
    version: float
    hatanaka: bool = False


def rinex_kind(path: str | Path) -> RinexKind | None:
    """The kind of RINEX file ``path`` is, or None when it is not RINEX (or cannot be read)."""
    lines = head_text(path, 512).splitlines()
    if not lines:
        return None
    hatanaka = "COMPACT RINEX FORMAT" in lines[0]
    if hatanaka:  # CRINEX VERS / TYPE and CRINEX PROG / DATE come first
        lines = [ln for ln in lines[1:4] if "RINEX VERSION" in ln]
    if not lines or "RINEX VERSION" not in lines[0]:
        return None
    first = lines[0]
    try:
        version = float(first[:9])
    except ValueError:
        return None
    ftype, sys_col = first[20:21].upper(), first[40:41].upper()
    if ftype == "O":
        return RinexKind("obs", sys_col.strip() or "G", version, hatanaka)
    if ftype == "C":
        return RinexKind("clock", sys_col.strip(), version)
    if version < 3 and ftype in _V2_NAV:
        return RinexKind("nav", _V2_NAV[ftype], version)
    if version >= 3 and ftype == "N":
        return RinexKind("nav", sys_col.strip() or "M", version)
    return RinexKind("other", sys_col.strip(), version)


def is_gnss_logger(path: str | Path) -> bool:
    """Whether ``path`` (plain or gzip) is an Android GnssLogger log, by its content: the app's header
    names a ``Version:`` and a ``Raw,`` record layout (or the file has Raw records at once), whatever the
    file is called (the app's own names match ``gnss_log*.txt``, shared logs often do not)."""
    head = head_text(path, 8192)
    return ("# Version:" in head and "Raw," in head) or head.startswith("Raw,")


def _candidates(folder: Path) -> list[Path]:
    out = []
    for d in (folder, folder / "supplemental"):
        if d.is_dir():
            out += sorted(p for p in d.iterdir() if p.is_file() and not p.name.lower().endswith(_TABLE_SUFFIXES))
    return out


def files_of_kind(folder: Path, kind: str) -> list[Path]:
    """Files in ``folder`` and ``folder/supplemental`` whose header says they are ``kind``."""
    out = []
    for p in _candidates(folder):
        k = rinex_kind(p)
        if k is not None and k.kind == kind:
            out.append(p)
    return out
