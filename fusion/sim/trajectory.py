"""Receiver trajectories for the simulator: smooth random drives and replays of real ones.

A :class:`Trajectory` is receive times (GPS ms) and ECEF positions. Random drives are
minimum-jerk (quintic) segments through random waypoints in the local horizontal plane, the
motion-primitive construction of Mueller et al. (2015) that the paper's simulator uses, with
car speeds. Replays read GSDC 2021 ``ground_truth.csv`` files.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pymap3d

from fusion.errors import DataError
from fusion.geometry import geodetic2ecef
# One figure for the whole package: the loader subtracts the same number (data/README.md).
from fusion.io.truth import GSDC2021_TRUTH_HEIGHT_ERROR_M as GSDC2021_HEIGHT_ERROR_M


@dataclass
class Trajectory:
    """t_ms: (E,) int64 GPS ms, strictly increasing; ecef: (E, 3) [m]; name: label;
    skipped: rows dropped when reading, by reason."""

    t_ms: np.ndarray
    ecef: np.ndarray
    name: str = "trajectory"
    skipped: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.t_ms = np.asarray(self.t_ms, np.int64)
        self.ecef = np.asarray(self.ecef, float)
        if self.t_ms.ndim != 1 or self.ecef.shape != (self.t_ms.shape[0], 3):
            raise DataError(f"{self.name}: trajectory shapes t_ms {self.t_ms.shape}, "
                            f"ecef {self.ecef.shape} do not match (E,), (E, 3)")
        if self.t_ms.size == 0:
            raise DataError(f"{self.name}: trajectory has no epochs")
        if np.any(np.diff(self.t_ms) <= 0):
            raise DataError(f"{self.name}: trajectory times are not strictly increasing")
        if not np.isfinite(self.ecef).all():
            raise DataError(f"{self.name}: trajectory has non-finite positions")

    def __len__(self) -> int:
        return int(self.t_ms.shape[0])

    def retimed(self, start_ms: int) -> "Trajectory":
        """The same path shifted in time so that it starts at ``start_ms``."""
        return Trajectory(self.t_ms - self.t_ms[0] + int(start_ms), self.ecef.copy(), self.name,
                          dict(self.skipped))


def _quintic_coeffs(p0, v0, a0, p1, v1, a1, T):
    """Coefficients c0..c5 (K, 6, D) of the minimum-jerk quintic meeting both end states."""
    T = T[:, None]
    c0, c1, c2 = p0, v0, a0 / 2.0
    # Solve the 3x3 end-condition system in closed form (standard minimum-jerk primitive).
    dp = p1 - (c0 + c1 * T + c2 * T**2)
    dv = v1 - (c1 + 2 * c2 * T)
    da = a1 - 2 * c2
    c3 = (10 * dp - 4 * dv * T + 0.5 * da * T**2) / T**3
    c4 = (-15 * dp + 7 * dv * T - da * T**2) / T**4
    c5 = (6 * dp - 3 * dv * T + 0.5 * da * T**2) / T**5
    return np.stack([c0, c1, c2, c3, c4, c5], axis=1)


def _eval_pieces(coeffs, t_knots, t, with_acc: bool = False):
    """Position, velocity (and acceleration) (N, D) of the piecewise quintic at times ``t``."""
    k = np.clip(np.searchsorted(t_knots, t, side="right") - 1, 0, len(coeffs) - 1)
    tau = (t - t_knots[k])[:, None]
    c = coeffs[k]
    pos = sum(c[:, j] * tau**j for j in range(6))
    vel = sum(j * c[:, j] * tau ** (j - 1) for j in range(1, 6))
    if not with_acc:
        return pos, vel
    acc = sum(j * (j - 1) * c[:, j] * tau ** (j - 2) for j in range(2, 6))
    return pos, vel, acc


def random_ne_path(duration_s: float, rate_hz: float, rng: np.random.Generator, *,
                   speed_range: tuple[float, float] = (0.0, 30.0), accel_max: float = 4.0,
                   leg_m: tuple[float, float] = (80.0, 500.0), turn_sigma_rad: float = 0.6
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Smooth horizontal path in a local north-east plane, sampled at ``rate_hz``.

    Waypoints are a random walk with legs of ``leg_m`` metres and heading changes
    N(0, ``turn_sigma_rad``). Each waypoint gets a random target speed in ``speed_range`` along
    the bisector of its legs, lowered so a car could take the turn (lateral acceleration
    v^2 / r <= ``accel_max`` on a corner of radius ~ half the shorter leg over tan(turn/2)),
    and zero acceleration; consecutive waypoints are joined by minimum-jerk quintics (Mueller et
    al. 2015). The whole path is then slowed until its sampled speed <= ``speed_range[1]`` and
    acceleration <= ``accel_max``.
    Returns (ne (N, 2) [m] relative to the start, speed (N,) [m/s]), N = floor(duration*rate)+1.
    """
    vmin, vmax = speed_range
    if not (0.0 <= vmin <= vmax) or vmax <= 0 or accel_max <= 0:
        raise ValueError(f"need 0 <= speed min <= max, max > 0, accel_max > 0; got {speed_range}, {accel_max}")
    n_samples = int(np.floor(duration_s * rate_hz + 1e-9)) + 1
    t = np.arange(n_samples) / rate_hz
    if n_samples == 1:
        return np.zeros((1, 2)), np.zeros(1)
    v_mean = max(0.5 * (vmin + vmax), 1.0)
    # Enough waypoints to outlast the duration even at the mean speed (slowing adds some).
    n_leg = int(np.ceil(2.0 * duration_s * v_mean / leg_m[0])) + 2
    turn = rng.normal(0.0, turn_sigma_rad, n_leg)
    heading = rng.uniform(0, 2 * np.pi) + np.cumsum(turn)
    length = rng.uniform(*leg_m, n_leg)
    unit = np.stack([np.cos(heading), np.sin(heading)], axis=1)
    way = np.vstack([np.zeros((1, 2)), np.cumsum(length[:, None] * unit, axis=0)])  # (K+1, 2)
    speed = rng.uniform(vmin, vmax, n_leg + 1)
    if vmin == 0:
        speed[0] = 0.0                                                   # start parked
    # Corner speed limit at interior waypoints: radius of a turn cutting half the shorter leg.
    ang = np.abs(np.angle(np.exp(1j * turn[1:])))
    radius = 0.5 * np.minimum(length[:-1], length[1:]) / np.maximum(np.tan(ang / 2), 1e-6)
    speed[1:-1] = np.minimum(speed[1:-1], np.sqrt(accel_max * radius))
    direction = np.vstack([unit[:1], unit[:-1] + unit[1:], unit[-1:]])
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
    vel = direction * speed[:, None]
    seg_speed = np.maximum(0.5 * (speed[:-1] + speed[1:]), 0.3 * v_mean)
    dur = length / seg_speed
    acc = np.zeros_like(way)
    for _ in range(30):  # slow the whole path down until both limits hold
        coeffs = _quintic_coeffs(way[:-1], vel[:-1], acc[:-1], way[1:], vel[1:], acc[1:], dur)
        knots = np.concatenate([[0.0], np.cumsum(dur)])
        fine = np.linspace(0.0, min(knots[-1], duration_s), 4 * n_samples)
        _, v_f, a_f = _eval_pieces(coeffs, knots, fine, with_acc=True)
        v_peak = np.linalg.norm(v_f, axis=1).max()
        a_peak = np.linalg.norm(a_f, axis=1).max()
        k = max(v_peak / vmax, np.sqrt(a_peak / accel_max))  # time x k: v / k, a / k^2
        if k <= 1.0 + 1e-9:
            break
        k *= 1.001
        dur, vel = dur * k, vel / k
    if knots[-1] < duration_s:  # ran out of path (only with extreme settings): hold still
        t = np.minimum(t, knots[-1])
    ne, v = _eval_pieces(coeffs, knots, t)[:2]
    return ne, np.linalg.norm(v, axis=1)


def check_rate(rate_hz: float) -> int:
    """Milliseconds per epoch; ValueError unless the rate gives a whole number of them."""
    if rate_hz <= 0 or 1000.0 / rate_hz != round(1000.0 / rate_hz):
        raise ValueError(f"rate_hz must give a whole number of milliseconds per epoch, got {rate_hz}")
    return int(round(1000.0 / rate_hz))


def parse_origins(origins_llh) -> np.ndarray:
    """One (lat, lon[, h]) row or a sequence of them (lengths may differ; h defaults to 0)
    -> (K, 3) float array; ValueError unless every row is finite with |lat| <= 90."""
    try:
        rows = [origins_llh] if np.ndim(origins_llh[0]) == 0 else list(origins_llh)
        if any(len(o) not in (2, 3) for o in rows):
            raise ValueError
        org = np.array([[float(v) for v in o] + [0.0] * (3 - len(o)) for o in rows])
    except (TypeError, ValueError, IndexError):
        raise ValueError(f"origins must be (lat, lon[, h]) rows, got {origins_llh!r}") from None
    if org.ndim != 2 or org.shape[0] == 0 or org.shape[1] != 3 or np.any(np.abs(org[:, 0]) > 90) \
            or not np.isfinite(org).all():
        raise ValueError(f"origins must be valid (lat, lon[, h]) rows, got {origins_llh!r}")
    return org


def ne_to_ecef(ne: np.ndarray, origin_llh: np.ndarray) -> np.ndarray:
    """Horizontal north/east offsets (N, 2) [m] from origins (N, 3) or (3,) -> ECEF (N, 3).

    The points keep their origin's ellipsoidal height: the offsets are mapped through geodetic
    coordinates, so long drives follow the Earth's curve instead of climbing off a tangent plane.
    """
    o = np.broadcast_to(np.asarray(origin_llh, float), (ne.shape[0], 3))
    lat, lon, _ = pymap3d.ned2geodetic(ne[:, 0], ne[:, 1], 0.0, o[:, 0], o[:, 1], o[:, 2])
    return geodetic2ecef(np.stack([lat, lon, o[:, 2]], axis=1))


def random_trajectory(origin_llh: tuple[float, float, float], n_epochs: int, start_ms: int,
                      rng: np.random.Generator, *, rate_hz: float = 1.0,
                      speed_range: tuple[float, float] = (0.0, 30.0), name: str = "sim") -> Trajectory:
    """A random smooth horizontal drive of ``n_epochs`` at ``rate_hz`` from ``origin_llh``."""
    return random_trajectories(np.asarray([origin_llh], float), n_epochs, np.array([start_ms]), rng,
                               rate_hz=rate_hz, speed_range=speed_range, names=[name])[0]


def random_trajectories(origins_llh: np.ndarray, n_epochs: int, start_ms: np.ndarray,
                        rng: np.random.Generator, *, rate_hz: float = 1.0,
                        speed_range: tuple[float, float] = (0.0, 30.0),
                        names: list[str] | None = None) -> list[Trajectory]:
    """One random drive per origin (K, 2|3) lat, lon[, h] and start time (K,) GPS ms.

    Paths are drawn one after the other from ``rng`` (so trace k is the same whatever K is
    beyond it); the geodetic conversion runs once for all of them.
    """
    if n_epochs < 1:
        raise ValueError(f"n_epochs must be >= 1, got {n_epochs}")
    step = check_rate(rate_hz)
    org = parse_origins(origins_llh)
    K = org.shape[0]
    ne = np.concatenate([random_ne_path((n_epochs - 1) / rate_hz, rate_hz, rng, speed_range=speed_range)[0]
                         for _ in range(K)])
    ecef = ne_to_ecef(ne, np.repeat(org, n_epochs, axis=0)).reshape(K, n_epochs, 3)
    t = np.asarray(start_ms, np.int64)[:, None] + step * np.arange(n_epochs, dtype=np.int64)
    names = names or [f"sim/{k:05d}" for k in range(K)]
    return [Trajectory(t[k], ecef[k], names[k]) for k in range(K)]


def load_gsdc_trajectory(path: str | Path, *, height_error_m: float = GSDC2021_HEIGHT_ERROR_M
                         ) -> Trajectory:
    """Replay a GSDC 2021 ``ground_truth.csv`` (latDeg, lngDeg, heightAboveWgs84EllipsoidM).

    ``height_error_m`` is subtracted from the file's heights (the GSDC 2021 geoid sign error);
    pass 0 for files without it. Rows with repeated / backwards times are dropped.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: ground-truth file not found")
    try:
        df = pd.read_csv(path)
    except (pd.errors.ParserError, UnicodeDecodeError, pd.errors.EmptyDataError) as exc:
        raise DataError(f"{path}: cannot parse CSV ({exc})") from None
    need = ["millisSinceGpsEpoch", "latDeg", "lngDeg", "heightAboveWgs84EllipsoidM"]
    missing = [c for c in need if c not in df.columns]
    if missing:
        raise DataError(f"{path}: missing column(s) {missing}")
    vals = df[need].apply(pd.to_numeric, errors="coerce")
    bad = vals.isna().any(axis=1).to_numpy()
    if bad.all():
        raise DataError(f"{path}: no readable rows")
    vals = vals[~bad]
    t = vals["millisSinceGpsEpoch"].to_numpy().round().astype(np.int64)
    keep = np.r_[True, t[1:] > np.maximum.accumulate(t)[:-1]]
    vals = vals[keep]
    llh = np.array(vals[["latDeg", "lngDeg", "heightAboveWgs84EllipsoidM"]].to_numpy(float))
    llh[:, 2] -= height_error_m
    name = f"{path.parent.parent.name}/{path.parent.name}"
    skipped = {k: int(n) for k, n in (("truth_rows_unreadable", bad.sum()),
                                      ("truth_rows_not_increasing", (~keep).sum())) if n}
    return Trajectory(t[keep], geodetic2ecef(llh), name, skipped)
