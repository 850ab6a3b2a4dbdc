"""The one measurement container every mode consumes.

A :class:`Trace` is a struct-of-arrays over ``E`` epochs and at most ``S`` satellite slots per
epoch. Epochs with fewer satellites are padded; ``mask`` says which slots are real. Padded slots
hold finite filler (zeros, ``pr_sigma`` = 1) so vectorised maths never meets NaN; code must
still multiply by ``mask`` (or index with it) before trusting a slot.

Conventions (see ARCHITECTURE.md):
- ``t_ms`` is the true receive time in integer GPS milliseconds (the GSDC 2021 one-second
  timestamp shift is already removed by the loader).
- ``sat_pos`` is ECEF at signal *transmit* time, not yet rotated for Earth rotation during
  flight: :func:`fusion.geometry.sagnac_rotate` does that at the receiver guess.
- ``pr`` is the corrected pseudorange (satellite clock, ISRB, iono, tropo removed), metres.
- ``truth`` is ECEF metres, NaN rows where no truth exists for that epoch; ``None`` when the
  source has no truth at all. Truth is for metrics and training targets only.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from fusion.errors import DataError, GnssfuseError

#: Signal names in the GSDC vocabulary; ``Trace.signal`` stores indices into this tuple. New
#: signals are appended (stored indices and checkpoints name signals by these positions): the
#: second frequencies a dual-frequency receiver logs (GPS L2C, Galileo E5b, BeiDou B2I, QZSS L2C), then
#: BeiDou-3's open signals on the L1 and L5 carriers (B1C, B2a), which newer phones log beside or instead of B1I.
SIGNALS: tuple[str, ...] = (
    "GPS_L1", "GPS_L5", "GLO_G1", "GAL_E1", "GAL_E5A", "BDS_B1I", "QZS_J1", "QZS_J5",
    "GPS_L2", "GAL_E5B", "BDS_B2I", "QZS_J2",
    "BDS_B1C", "BDS_B2A",
)


def satellite_counts(sat_id: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """(E,) int distinct satellites among the slots ``sel`` (E,S) bool, ``sat_id`` (E,S) int: a second
    frequency of a satellite adds a pseudorange but no direction, so four slots of two satellites fix no
    position. A slot without a satellite number (0: arrays built without one) counts as a satellite of its own."""
    sat_id = np.asarray(sat_id, np.int64)
    own = -1 - np.arange(sat_id.shape[1])              # one per slot, below every real number
    none = np.iinfo(np.int64).min
    ids = np.sort(np.where(sel, np.where(sat_id > 0, sat_id, own), none), axis=1)
    new = ids[:, 1:] != ids[:, :-1]
    return (ids[:, :1] != none).sum(axis=1) + (new & (ids[:, 1:] != none)).sum(axis=1)


def signal_index(names: Sequence[str] | pd.Series) -> np.ndarray:
    """Map GSDC signal names onto indices into :data:`SIGNALS` (int8, -1 where unknown).

    2021/2022 names are ours already (``GPS_L1``); 2023 adds a code suffix (``GPS_L1_CA``,
    ``GAL_E1_C_P``, ``GAL_E5A_Q``), which is dropped: the first two ``_`` tokens name the signal.
    """
    s = pd.Series(names, dtype=object)
    lookup = {}
    for name in s.dropna().unique():
        key = str(name).strip().upper()
        short = "_".join(key.split("_")[:2])
        lookup[name] = SIGNALS.index(key) if key in SIGNALS else (
            SIGNALS.index(short) if short in SIGNALS else -1)
    return s.map(lookup).fillna(-1).to_numpy(np.int8)


def resolve_signals(signals: Sequence[str] | str | None) -> np.ndarray:
    """User signal selection -> sorted unique indices into :data:`SIGNALS`.

    ``None``, ``"all"`` or a sequence containing ``"all"`` (any case) selects every known signal;
    names may use 2023 spellings.
    """
    if isinstance(signals, str):
        signals = [signals]
    if signals is None or any(str(s).strip().lower() == "all" for s in signals):
        return np.arange(len(SIGNALS))
    idx = signal_index(list(signals))
    unknown = [s for s, i in zip(signals, idx) if i < 0]
    if unknown or len(idx) == 0:
        raise GnssfuseError(f"unknown signal name(s) {unknown or list(signals)}; known: {', '.join(SIGNALS)}")
    return np.unique(idx)


@dataclass
class Trace:
    """Padded per-epoch GNSS measurements of one phone on one drive.

    Shapes: ``E`` epochs, ``S`` satellite slots.

    t_ms:        (E,)     int64, receive time, GPS milliseconds.
    sat_pos:     (E,S,3)  float64, satellite ECEF at transmit time [m].
    sat_vel:     (E,S,3)  float64, satellite ECEF velocity [m/s] (zeros when unknown).
    pr:          (E,S)    float64, corrected pseudorange [m].
    pr_sigma:    (E,S)    float64, reported 1-sigma pseudorange uncertainty [m].
    sat_id:      (E,S)    int32, ``1000 * constellationType + svid`` (GPS PRN 5 -> 1005).
    signal:      (E,S)    int8, index into :data:`SIGNALS`.
    mask:        (E,S)    bool, True where the slot holds a real measurement.
    clock_reset: (E,)     bool, True where the receiver clock is known/suspected to have jumped
                          since the previous epoch (first epoch is False).
    truth:       (E,3)    float64 ECEF truth [m] with NaN rows where unknown, or None.
    name:        ``"<collection>/<phone>"`` or a file stem.
    skipped:     counts of dropped rows / epochs by reason, for the user's report.

    Optional per-slot measurements (None when the source has none; padded slots hold 0 / False):

    cn0:         (E,S)    float64, carrier-to-noise density [dB-Hz]; 0 where unknown.
    pr_sigma_ok: (E,S)    bool, ``pr_sigma`` is the receiver's own report (False: a model filled it in,
                          e.g. from C/N0 for RINEX, which reports none); None: reported wherever real.
    prr:         (E,S)    float64, pseudorange rate from Doppler [m/s] (``-wavelength * doppler``),
                          satellite clock drift removed (``+ c * d(dt_sv)/dt``), like ``pr``.
    prr_sigma:   (E,S)    float64, its 1-sigma [m/s] (1 where not ``prr_ok``).
    prr_ok:      (E,S)    bool, the slot has a usable Doppler.
    adr:         (E,S)    float64, accumulated delta range (carrier phase) [m], satellite clock
                          removed (``+ c * dt_sv``), so that between two epochs without a slip
                          ``diff(adr) = diff(range) + diff(receiver clock)`` (+ noise, iono change).
    adr_sigma:   (E,S)    float64, its 1-sigma [m] (1 where not ``adr_ok``).
    adr_ok:      (E,S)    bool, the slot has a valid carrier phase.
    adr_slip:    (E,S)    bool, the carrier phase of this slot's satellite/signal was reset or
                          slipped since the previous epoch (its chain must break here).
    odometry:    (E,12)   float64 vehicle odometry per epoch, columns :data:`ODOMETRY_COLUMNS` (body
                          frame: x forward, z up), NaN rows where none; None when the source has none.
    """

    t_ms: np.ndarray
    sat_pos: np.ndarray
    sat_vel: np.ndarray
    pr: np.ndarray
    pr_sigma: np.ndarray
    sat_id: np.ndarray
    signal: np.ndarray
    mask: np.ndarray
    clock_reset: np.ndarray
    truth: np.ndarray | None = None
    name: str = "trace"
    skipped: dict[str, int] = field(default_factory=dict)
    cn0: np.ndarray | None = None
    pr_sigma_ok: np.ndarray | None = None
    prr: np.ndarray | None = None
    prr_sigma: np.ndarray | None = None
    prr_ok: np.ndarray | None = None
    adr: np.ndarray | None = None
    adr_sigma: np.ndarray | None = None
    adr_ok: np.ndarray | None = None
    adr_slip: np.ndarray | None = None
    odometry: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.validate()

    # ------------------------------------------------------------------ shape checks
    def validate(self) -> None:
        """Raise :class:`DataError` naming the field whose shape or dtype is wrong."""
        E = np.shape(self.t_ms)[0] if np.ndim(self.t_ms) == 1 else -1
        if E < 0:
            raise DataError(f"{self.name}: t_ms must be 1-D, got shape {np.shape(self.t_ms)}")
        S = np.shape(self.pr)[1] if np.ndim(self.pr) == 2 else -1
        expected = {
            "sat_pos": (E, S, 3), "sat_vel": (E, S, 3), "pr": (E, S), "pr_sigma": (E, S),
            "sat_id": (E, S), "signal": (E, S), "mask": (E, S), "clock_reset": (E,),
        }
        for key, shape in expected.items():
            got = np.shape(getattr(self, key))
            if got != shape:
                raise DataError(f"{self.name}: {key} has shape {got}, expected {shape}")
        self._validate_optional(E, S)
        if self.odometry is not None and np.shape(self.odometry) != (E, len(ODOMETRY_COLUMNS)):
            raise DataError(f"{self.name}: odometry has shape {np.shape(self.odometry)}, "
                            f"expected {(E, len(ODOMETRY_COLUMNS))}")
        if self.truth is not None and np.shape(self.truth) != (E, 3):
            raise DataError(f"{self.name}: truth has shape {np.shape(self.truth)}, expected {(E, 3)}")
        if self.mask.dtype != bool:
            raise DataError(f"{self.name}: mask must be bool, got {self.mask.dtype}")
        m = self.mask
        for key in ("sat_pos", "pr", "pr_sigma"):
            if not np.all(np.isfinite(getattr(self, key)[m])):
                raise DataError(f"{self.name}: {key} has non-finite values in unmasked slots")
        if E > 1 and np.any(np.diff(self.t_ms) <= 0):
            raise DataError(f"{self.name}: epoch times are not strictly increasing")

    def _validate_optional(self, E: int, S: int) -> None:
        """The optional per-slot arrays: all of a group or none, each (E,S), flags bool."""
        for group in OPTIONAL_GROUPS:
            have = [getattr(self, k) is not None for k in group]
            if any(have) and not all(have):
                raise DataError(f"{self.name}: {', '.join(group)} must be given together")
        for key in OPTIONAL_SLOT_FIELDS:
            a = getattr(self, key)
            if a is None:
                continue
            if np.shape(a) != (E, S):
                raise DataError(f"{self.name}: {key} has shape {np.shape(a)}, expected {(E, S)}")
            if key in ("pr_sigma_ok", "prr_ok", "adr_ok", "adr_slip") and np.asarray(a).dtype != bool:
                raise DataError(f"{self.name}: {key} must be bool, got {np.asarray(a).dtype}")
        for value, ok in (("prr", "prr_ok"), ("adr", "adr_ok")):
            if getattr(self, ok) is not None and not np.all(np.isfinite(getattr(self, value)[getattr(self, ok)])):
                raise DataError(f"{self.name}: {value} has non-finite values in slots flagged {ok}")

    @property
    def has_doppler(self) -> bool:
        return self.prr_ok is not None and bool((self.prr_ok & self.mask).any())

    @property
    def has_carrier(self) -> bool:
        return self.adr_ok is not None and bool((self.adr_ok & self.mask).any())

    # ------------------------------------------------------------------ convenience
    @property
    def n_epochs(self) -> int:
        return int(self.t_ms.shape[0])

    @property
    def n_slots(self) -> int:
        return int(self.pr.shape[1])

    @property
    def n_sats(self) -> np.ndarray:
        """(E,) number of real measurements per epoch."""
        return self.mask.sum(axis=1)

    @property
    def has_truth(self) -> bool:
        return self.truth is not None and bool(np.isfinite(self.truth).all(axis=1).any())

    def select(self, epochs: np.ndarray) -> "Trace":
        """A new Trace with only the given epochs (bool mask (E,) or ascending integer indices).

        Slot padding is trimmed to the widest remaining epoch. A clock jump flagged on a dropped
        epoch moves to the next kept one: the receiver clock still jumped between the two kept
        epochs, and an estimator that missed it would chain the clock across the jump.
        """
        try:
            idx = np.arange(self.n_epochs)[epochs]
        except IndexError as exc:
            raise DataError(f"{self.name}: cannot select epochs of a {self.n_epochs}-epoch trace "
                            f"({exc})") from None
        reset, gap = flags_since_previous(self.clock_reset, idx)
        reset[:1] = self.clock_reset[idx[:1]]
        mask = self.mask[idx]
        S = max(int(mask.sum(axis=1).max(initial=0)), 1)
        # Compact real slots to the front so trimming to S loses nothing.
        order = np.argsort(~mask, axis=1, kind="stable")[:, :S]

        def take(a: np.ndarray) -> np.ndarray:
            a = a[idx]
            if a.ndim == 3:
                return np.take_along_axis(a, order[..., None], axis=1)
            return np.take_along_axis(a, order, axis=1)

        optional = {k: take(getattr(self, k)) for k in OPTIONAL_SLOT_FIELDS if getattr(self, k) is not None}
        if "adr_slip" in optional:
            # a slip on a dropped epoch, or one hidden in a gap, breaks the chain across it
            optional["adr_slip"] = optional["adr_slip"] | gap[:, None]
        return replace(
            self,
            t_ms=self.t_ms[idx], sat_pos=take(self.sat_pos), sat_vel=take(self.sat_vel),
            pr=take(self.pr), pr_sigma=take(self.pr_sigma), sat_id=take(self.sat_id),
            signal=take(self.signal), mask=take(self.mask), clock_reset=reset,
            truth=None if self.truth is None else self.truth[idx], skipped=dict(self.skipped), **optional,
            odometry=None if self.odometry is None else self.odometry[idx],
        )

    def select_slots(self, keep: np.ndarray) -> "Trace":
        """A new Trace whose mask is ``mask & keep`` (keep: (E,S) bool), e.g. a signal filter."""
        return replace(self, mask=self.mask & keep).select(np.ones(self.n_epochs, bool))

    def count_skip(self, reason: str, n) -> None:
        count_skip(self.skipped, reason, n)


#: Optional per-slot fields of :class:`Trace` (None when the source has none).
OPTIONAL_SLOT_FIELDS = ("cn0", "pr_sigma_ok", "prr", "prr_sigma", "prr_ok", "adr", "adr_sigma", "adr_ok", "adr_slip")
#: Columns of ``Trace.odometry``: body velocity [m/s], turn rate [rad/s], and their variances.
ODOMETRY_COLUMNS = ("vx", "vy", "vz", "wx", "wy", "wz", "var_vx", "var_vy", "var_vz", "var_wx", "var_wy", "var_wz")
#: Fields that come together or not at all.
OPTIONAL_GROUPS = (("prr", "prr_sigma", "prr_ok"), ("adr", "adr_sigma", "adr_ok", "adr_slip"))


def flags_since_previous(flags: np.ndarray, kept: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Carry per-epoch events across dropped epochs.

    flags: (E,) bool per original epoch (e.g. a clock reset); kept: (K,) ascending indices of the
    epochs that stay. Returns (K,) ``flagged``: True where the flag is set on the kept epoch or on
    any dropped epoch since the previous kept one (the event still happened between the two), and
    (K,) ``gap``: True where epochs were dropped since the previous kept one. Both False at the
    first kept epoch, which has no previous one.
    """
    kept = np.asarray(kept, np.int64)
    cum = np.r_[0, np.cumsum(np.asarray(flags, bool))]
    flagged = np.zeros(kept.size, bool)
    gap = np.zeros(kept.size, bool)
    flagged[1:] = cum[kept[1:] + 1] - cum[kept[:-1] + 1] > 0
    gap[1:] = np.diff(kept) > 1
    return flagged, gap


def trace_folder_name(folder: Path) -> str:
    """The name of the trace in ``folder``: ``<collection>/<phone>``, also when given as ``.`` or ``phone``."""
    folder = Path(folder).resolve()
    return f"{folder.parent.name}/{folder.name}"


def count_skip(skipped: dict[str, int], key: str, n) -> None:
    """Add ``n`` (a count, or a bool selection whose True entries are counted) to
    ``skipped[key]``; zero adds no key, so reports list only reasons that happened."""
    n = int(np.sum(n))
    if n:
        skipped[key] = skipped.get(key, 0) + n


def empty_trace(E: int, S: int, name: str = "trace", with_truth: bool = False) -> dict:
    """Zero-filled keyword arguments for :class:`Trace` of shape (E, S); loaders fill them in."""
    return dict(
        t_ms=np.zeros(E, np.int64), sat_pos=np.zeros((E, S, 3)), sat_vel=np.zeros((E, S, 3)),
        pr=np.zeros((E, S)), pr_sigma=np.ones((E, S)), sat_id=np.zeros((E, S), np.int32),
        signal=np.zeros((E, S), np.int8), mask=np.zeros((E, S), bool),
        clock_reset=np.zeros(E, bool),
        truth=np.full((E, 3), np.nan) if with_truth else None, name=name,
    )


def pack_rows(epoch_index: np.ndarray, n_epochs: int, columns: dict[str, np.ndarray]) -> dict:
    """Scatter row-major measurements into padded (E, S[, k]) arrays without a Python loop.

    epoch_index: (N,) int, epoch of each row, sorted ascending.
    columns:     name -> (N,) or (N, k) array.
    Returns name -> (E, S) / (E, S, k) arrays plus ``mask`` (E, S).
    """
    N = epoch_index.shape[0]
    counts = np.bincount(epoch_index, minlength=n_epochs)
    S = max(int(counts.max(initial=0)), 1)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(N) - starts[epoch_index]
    out: dict[str, np.ndarray] = {}
    for key, col in columns.items():
        filler = 1.0 if key.endswith("_sigma") else 0
        arr = np.full((n_epochs, S) + col.shape[1:], filler, dtype=col.dtype)
        arr[epoch_index, slot] = col
        out[key] = arr
    mask = np.zeros((n_epochs, S), bool)
    mask[epoch_index, slot] = True
    out["mask"] = mask
    return out


def cn0_sigma_factor(cn0_dbhz: np.ndarray, ref_dbhz: float) -> np.ndarray:
    """(...) factor >= 1 on a tracking loop's noise sigma for C/N0 below ``ref_dbhz``: 10^((ref - C/N0) / 20),
    the amplitude-noise scaling of code and carrier tracking; 1 at or above it. cn0_dbhz (...) [dB-Hz]."""
    return 10.0 ** (np.clip(ref_dbhz - np.asarray(cn0_dbhz, float), 0.0, None) / 20.0)
