"""One way to open a measurement or product file: plain, gzip or Hatanaka-compressed, by content.

Every reader in :mod:`fusion.io` gets its bytes from :func:`read_bytes` (or lines from
:func:`read_lines`), so a ``.gz`` is decompressed whatever its name says, a file named ``.gz``
that is not gzip is refused, and a gzip stream cut short keeps what was decompressed (counted
``truncated_gzip``, with a warning). :func:`head_text` reads only the first kilobytes, for
telling files apart by their header (:mod:`fusion.io.discover`).

Hatanaka-compressed RINEX observations (CRINEX: ``.crx``, ``.YYd``, what reference stations
publish) are expanded with the PyPI package ``hatanaka`` (its bundled C ``crx2rnx``), detected
by the ``COMPACT RINEX FORMAT`` first line, not the name.
"""
from __future__ import annotations

import gzip
import warnings
import zlib
from pathlib import Path

from fusion.errors import DataError
from fusion.trace import count_skip

GZIP_MAGIC = b"\x1f\x8b"
CRINEX_MARK = b"COMPACT RINEX FORMAT"


def _gunzip(path: Path, raw: bytes, what: str, skipped: dict[str, int] | None) -> bytes:
    """Decompress ``raw``; a stream that stops early keeps its decompressed part (counted)."""
    try:
        return gzip.decompress(raw)
    except EOFError:
        pass
    except (gzip.BadGzipFile, zlib.error, OSError) as exc:
        raise DataError(f"{path}: corrupt gzip {what} file ({exc})") from exc
    # wbits 16+: gzip header; a decompressobj returns what it has without demanding the trailer
    try:
        part = zlib.decompressobj(16 + zlib.MAX_WBITS).decompress(raw)
    except zlib.error as exc:
        raise DataError(f"{path}: corrupt gzip {what} file ({exc})") from exc
    if not part:
        raise DataError(f"{path}: corrupt gzip {what} file (ends before any data)")
    count_skip(skipped if skipped is not None else {}, "truncated_gzip", 1)
    warnings.warn(f"{path}: gzip stream ends early; reading the {len(part)} bytes before the cut",
                  stacklevel=4)
    return part


def read_bytes(path: str | Path, what: str, skipped: dict[str, int] | None = None, *,
               crinex: bool = False) -> bytes:
    """The file's content, gunzipped when it starts with the gzip magic bytes.

    ``crinex``: expand Hatanaka-compressed RINEX (observation readers only).
    Raises :class:`DataError` naming the file when it is missing, unreadable, or named ``.gz``
    without being gzip.
    """
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: a folder, not a {what} file")
    if path.exists() and not path.is_file():
        raise DataError(f"{path}: not a regular file (a device or pipe?), not a {what} file")
    if not path.is_file():
        raise DataError(f"{path}: {what} file not found")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DataError(f"{path}: cannot read {what} file: {exc.strerror or exc}") from None
    if raw[:2] == GZIP_MAGIC:
        raw = _gunzip(path, raw, what, skipped)
    elif path.name.lower().endswith(".gz") and raw:
        raise DataError(f"{path}: corrupt gzip {what} file (no gzip header)")
    if crinex and CRINEX_MARK in raw[:80]:
        raw = _crx2rnx(path, raw)
    return raw


def read_lines(path: str | Path, what: str, skipped: dict[str, int] | None = None) -> list[str]:
    """The file's lines as ASCII text (undecodable bytes replaced), plain or gzipped."""
    return read_bytes(path, what, skipped).decode("ascii", errors="replace").splitlines()


def head_text(path: str | Path, n_bytes: int = 4096) -> str:
    """The first ``n_bytes`` of the (decompressed) file as text; '' when it cannot be read.

    For sniffing only: never raises, so a folder scan skips what it cannot open.
    """
    try:
        with open(path, "rb") as fh:
            magic = fh.read(2)
            fh.seek(0)
            data = gzip.GzipFile(fileobj=fh).read(n_bytes) if magic == GZIP_MAGIC else fh.read(n_bytes)
    except (OSError, EOFError, zlib.error):
        return ""
    return data.decode("ascii", errors="replace")


def _crx2rnx(path: Path, raw: bytes) -> bytes:
    """Hatanaka-expanded RINEX text of a CRINEX file's bytes."""
    try:
        import hatanaka
    except ImportError:
        raise DataError(f"{path}: Hatanaka-compressed (CRINEX) file and the 'hatanaka' package is not "
                        "installed (pip install hatanaka)") from None
    try:
        return hatanaka.crx2rnx(raw)
    except Exception as exc:  # the C tool reports any defect of the file; ours is one line naming it
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{path}: cannot expand Hatanaka-compressed file ({msg})") from None
