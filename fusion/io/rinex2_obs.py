"""RINEX 2.10-2.12 observation records: where each satellite's observations are, and their values.

RINEX 2 has no record marker: an epoch line (``yy mm dd hh mm ss.sssssss  f nnn`` + up to 12
satellites, continued on further lines) is followed by ``ceil(types / 5)`` lines per satellite, so
the record layout is found by one walk over the epoch lines (a few microseconds each); all values
are then read at once by :mod:`fusion.io.fixed_width` like RINEX 3. Observation types become RINEX 3
codes (:func:`fusion.io.rinex_obs.v2_type_as_v3`) so the same signal table applies.
"""
from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from fusion.errors import DataError
from fusion.io.fixed_width import char_matrix, cut_inside_a_number, gather_fields, line_bounds
from fusion.trace import count_skip

_PER_LINE_SATS = 12
_PER_LINE_OBS = 5
_FIELD = 16


def walk_records(body: np.ndarray, n_types: int, first_line_no: int, path: Path,
                 skipped: dict[str, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Epoch records of a RINEX 2 body.

    body: (B,) uint8 after the header.  first_line_no: file line number of the body's first line.
    Returns ``(epoch_line, n_sat, flag, obs_start)``, each (K,) over observation epochs (flags 0
    and 1): line index of the epoch line, satellite count, flag, line index of the first
    observation line. Event (2-5) and cycle-slip (6) records are skipped and counted; a record
    the file ends inside is counted as truncated, with a warning.
    """
    starts, ends = line_bounds(body)
    per_sat = -(-n_types // _PER_LINE_OBS)
    out: list[tuple[int, int, int, int]] = []
    i, n_lines = 0, starts.size
    while i < n_lines:
        if ends[i] <= starts[i]:
            i += 1
            continue
        text = body[starts[i]:ends[i]].tobytes().decode("ascii", errors="replace")
        try:
            flag, n = int(text[28:29] or 0), int(text[29:32])
        except ValueError:
            raise DataError(f"{path}:{first_line_no + i}: cannot read epoch line {text.rstrip()!r}") from None
        if 2 <= flag <= 5:
            count_skip(skipped, "event_records", 1)
            i += 1 + n
            continue
        n_list = max(1, -(-n // _PER_LINE_SATS))
        size = n_list + n * per_sat
        if i + size > n_lines or (i + size == n_lines and body[-1] != 10
                                  and cut_inside_a_number(int(ends[-1] - starts[-1]), 0)):
            warnings.warn(f"{path}:{first_line_no + i}: last epoch record is truncated; skipped", stacklevel=4)
            count_skip(skipped, "records_truncated", 1)
            break
        if flag == 6:
            count_skip(skipped, "cycle_slip_records", 1)
        else:
            out.append((i, n, flag, i + n_list))
        i += size
    if not out:
        return (np.zeros(0, np.int64),) * 4
    return tuple(np.array(col, np.int64) for col in zip(*out))


def satellite_fields(body: np.ndarray, epoch_line: np.ndarray, n_sat: np.ndarray, obs_start: np.ndarray,
                     n_types: int) -> tuple[np.ndarray, ...]:
    """Satellite ids and observation fields of every satellite of the given epochs.

    epoch_line, n_sat, obs_start: (K,) from :func:`walk_records`.
    Returns ``(epoch_of, system, prn_chars, fields, first_line)``: (M,) epoch index, (M,) uint8
    system letter (blank -> ``G``), (M, 2) uint8 satellite-number characters, (16, M, n_types)
    uint8 column-major F14.3 + LLI + SSI fields and (M,) line index of each satellite's first line.
    """
    starts, ends = line_bounds(body)
    epoch_of = np.repeat(np.arange(n_sat.size), n_sat)
    k = np.arange(epoch_of.size) - np.repeat(np.cumsum(n_sat) - n_sat, n_sat)  # satellite within epoch
    list_line = epoch_line[epoch_of] + k // _PER_LINE_SATS
    sat = char_matrix(body, starts[list_line], ends[list_line], 32 + 3 * _PER_LINE_SATS)
    col = 32 + 3 * (k % _PER_LINE_SATS)
    rows = np.arange(k.size)
    system = sat[rows, col]
    system = np.where(system == 32, np.uint8(ord("G")), system)
    prn_chars = np.stack([sat[rows, col + 1], sat[rows, col + 2]], axis=1)
    per_sat = -(-n_types // _PER_LINE_OBS)
    first = obs_start[epoch_of] + k * per_sat
    parts = [gather_fields(body, starts[first + j], ends[first + j], _FIELD * np.arange(_PER_LINE_OBS), _FIELD)
             for j in range(per_sat)]
    fields = np.concatenate(parts, axis=2)[:, :, :n_types]
    return epoch_of, system, prn_chars, np.ascontiguousarray(fields), first
