"""Urban canyon: street-side buildings along the trajectory decide, per satellite and epoch, whether
a signal arrives directly (LOS), only by a reflection off a facade (NLOS), bent over a roof edge
(diffracted), or not at all (blocked).

Streets. The drive is cut into streets by distance travelled (lengths U[``street_length_m``],
a new street at every trace start). A street runs along the chord of the drive over it; its width
(facade to facade) is U[``width_m``], the receiver's lane a random offset of up to a quarter width
from its centre line, and each side has a building of height U[``height_m``] or, with probability
``gap_prob``, none (a cross street, a car park). As the receiver moves sideways within the street
its distance to each facade changes (never below ``min_wall_m``: a facade held there moves with the
receiver, and its reflection gets no Doppler error).

Geometry (all closed form, vectorised over (E, P)). A satellite at elevation ``el`` and azimuth
``alpha`` relative to the street has horizontal direction component ``s = sin(alpha)`` towards the
right-hand facade (``s > 0``: the satellite is over the right-hand buildings). With ``w_n, H_n`` the
near (satellite-side) facade's distance and height, ``w_o, H_o`` the opposite one's and ``h`` the
antenna height:

- LOS  when ``w_n tan(el) >= (H_n - h) |s|`` (the ray clears the near roof; the mask elevation is
  ``atan((H_n - h) |s| / w_n)``, 0 along the street);
- NLOS when the direct ray is blocked, the specular reflection point on the opposite facade lies
  below its roof (``w_o tan(el) < (H_o - h) |s|``) and the incoming ray clears the near roof
  (``(2 w_o + w_n) tan(el) > (H_n - h) |s|``). The reflected path is the direct path from the
  receiver mirrored in the facade: extra delay ``2 w_o cos(el) |s|`` > 0, and its rate
  ``2 cos(el) s (v . n_R)`` with ``n_R`` the street's right-hand normal and ``v`` the receiver
  velocity (only motion towards/away from the facade changes a specular path: a car driving
  parallel to the wall sees no NLOS Doppler error, one changing lanes or turning does);
  the power loss is U[``reflection_loss_db``] per (street, satellite);
- diffracted when neither, but the satellite is less than ``diffraction_deg`` below the mask:
  loss 6 dB at the roof edge growing linearly to ``diffraction_max_db``, extra delay the detour over
  the edge ``d_edge (1 - cos(depth))`` (centimetres), no Doppler error;
- blocked otherwise.

The satellites' own motion changes the NLOS delay by millimetres per second; it is left out of the
Doppler error. Line-of-sight multipath (:func:`los_multipath`) adds a slowly oscillating code
error whose amplitude grows as C/N0 falls.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fusion.geometry import ned_rotation

LOS, NLOS, DIFFRACTED, BLOCKED = 0, 1, 2, 3
#: Names of the classes in label files.
CLASS_NAMES = ("LOS", "NLOS", "DIFFRACTED", "BLOCKED")


@dataclass
class CanyonModel:
    """Street and building statistics (metres, dB, degrees, seconds); see module docstring."""

    height_m: tuple[float, float] = (15.0, 60.0)
    width_m: tuple[float, float] = (15.0, 35.0)
    gap_prob: float = 0.15
    street_length_m: tuple[float, float] = (40.0, 150.0)
    antenna_height_m: float = 1.5
    min_wall_m: float = 2.0
    reflection_loss_db: tuple[float, float] = (5.0, 15.0)
    diffraction_deg: float = 3.0
    diffraction_max_db: float = 20.0

    def validate(self) -> None:
        for name in ("height_m", "width_m", "street_length_m", "reflection_loss_db"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise ValueError(f"canyon {name} must be (lo, hi) with 0 <= lo <= hi, got {(lo, hi)}")
        if self.street_length_m[0] <= 0 or self.width_m[0] < 2 * self.min_wall_m or not 0 <= self.gap_prob <= 1:
            raise ValueError(f"bad canyon settings: street_length_m {self.street_length_m}, width_m "
                             f"{self.width_m} (>= 2 min_wall_m), gap_prob {self.gap_prob}")


def _streets(ne: np.ndarray, trace_start: np.ndarray, model: CanyonModel, rng: np.random.Generator
             ) -> np.ndarray:
    """(E,) street index (0..n-1, non-decreasing) of each epoch from the distance travelled."""
    step = np.r_[0.0, np.linalg.norm(np.diff(ne, axis=0), axis=1)]
    lo, hi = model.street_length_m
    # a jump of `hi` at each trace start puts at least one street boundary between two traces
    dist = np.cumsum(np.where(trace_start, hi, step))
    bounds = np.cumsum(rng.uniform(lo, hi, int(dist[-1] // lo) + 2))
    raw = np.searchsorted(bounds, dist, side="right")
    return np.unique(raw, return_inverse=True)[1].reshape(-1)


def street_layout(rx: np.ndarray, trace_start: np.ndarray, model: CanyonModel,
                  rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Per-epoch street geometry along the true track.

    rx (E,3) ECEF; trace_start (E,) bool. Returns street (E,) int, azimuth_rad (E,) street direction
    (clockwise from north), normal_ne (E,2) right-hand normal in (north, east), w_right / w_left (E,)
    facade distances [m], right_held / left_held (E,) bool where that distance is held at
    ``min_wall_m``, h_right / h_left (E,) building heights [m] (0 = none), and the
    per-street reflection loss draw ``refl_u`` (n_streets, 1) in [0, 1) for :func:`classify`.
    """
    first = np.flatnonzero(trace_start)
    tid = np.cumsum(trace_start) - 1
    R = ned_rotation(rx[first])                                       # (T,3,3) at each trace start
    ne = np.einsum("eij,ej->ei", R[tid], rx - rx[first][tid])[:, :2]
    street = _streets(ne, trace_start, model, rng)
    n = int(street[-1]) + 1
    start = np.r_[0, np.flatnonzero(np.diff(street)) + 1]
    end = np.r_[start[1:], street.size] - 1
    chord = ne[end] - ne[start]
    az = np.where(np.linalg.norm(chord, axis=1) > 1.0, np.arctan2(chord[:, 1], chord[:, 0]),
                  rng.uniform(0, 2 * np.pi, n))
    centre = np.add.reduceat(ne, start, axis=0) / np.diff(np.r_[start, street.size])[:, None]
    normal = np.stack([-np.sin(az), np.cos(az)], axis=1)              # (n,2) right-hand, (N,E)
    width = rng.uniform(*model.width_m, n)
    lane = rng.uniform(-0.25, 0.25, n) * width
    heights = rng.uniform(*model.height_m, (n, 2)) * (rng.random((n, 2)) >= model.gap_prob)
    lateral = np.einsum("ej,ej->e", ne - centre[street], normal[street]) + lane[street]
    half = 0.5 * width[street]
    w_right, w_left = half - lateral, half + lateral
    return dict(street=street, azimuth_rad=az[street], normal_ne=normal[street],
                w_right=np.maximum(w_right, model.min_wall_m), w_left=np.maximum(w_left, model.min_wall_m),
                # a facade held at min_wall_m moves with the receiver: its reflection has no rate
                right_held=w_right < model.min_wall_m, left_held=w_left < model.min_wall_m,
                h_right=heights[street, 0], h_left=heights[street, 1], refl_u=rng.random((n, 1)), ne=ne)


def classify(el_deg: np.ndarray, az_deg: np.ndarray, layout: dict[str, np.ndarray], vel_ne: np.ndarray,
             model: CanyonModel, cols: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """LOS / NLOS / diffracted / blocked per (epoch, satellite), with the error each class brings.

    el_deg, az_deg (E,P) at the receiver; layout from :func:`street_layout`; vel_ne (E,2) receiver
    velocity (north, east) [m/s]; cols: int satellite ids, broadcastable to (E,P), for the
    per-(street, satellite) reflection loss (default 0..P-1; two signals of one satellite share it).
    Returns cls (E,P) int8, delay_m (E,P) >= 0, loss_db (E,P) >= 0, rate_err_mps (E,P), mask_deg (E,P).
    """
    el = np.radians(np.clip(el_deg, 0.0, 90.0))
    alpha = np.radians(az_deg) - layout["azimuth_rad"][:, None]
    s = np.sin(alpha)
    right = s > 0
    w_n = np.where(right, layout["w_right"][:, None], layout["w_left"][:, None])
    w_o = np.where(right, layout["w_left"][:, None], layout["w_right"][:, None])
    h0 = model.antenna_height_m
    hn = np.where(right, layout["h_right"][:, None], layout["h_left"][:, None]) - h0
    ho = np.where(right, layout["h_left"][:, None], layout["h_right"][:, None]) - h0
    tan_el, a = np.tan(el), np.abs(s)
    los = w_n * tan_el >= hn * a
    refl = ~los & (w_o * tan_el < ho * a) & ((2 * w_o + w_n) * tan_el > hn * a)
    mask = np.arctan2(np.maximum(hn, 0.0) * a, w_n)
    depth = mask - el
    diff = ~los & ~refl & (depth < np.radians(model.diffraction_deg))
    cls = np.full(el.shape, BLOCKED, np.int8)
    cls[los], cls[refl], cls[diff] = LOS, NLOS, DIFFRACTED
    cos_el = np.cos(el)
    d_edge = w_n / np.maximum(a, 1e-6) / np.maximum(np.cos(mask), 1e-6)
    delay = np.where(refl, 2.0 * w_o * cos_el * a, np.where(diff, d_edge * (1.0 - np.cos(depth)), 0.0))
    v_perp = np.einsum("ej,ej->e", vel_ne, layout["normal_ne"])[:, None]
    held = np.where(right, layout["left_held"][:, None], layout["right_held"][:, None])
    rate = np.where(refl & ~held, 2.0 * cos_el * s * v_perp, 0.0)
    cols = np.arange(el.shape[1])[None, :] if cols is None else cols
    u = _hash_uniform(layout["street"][:, None], cols, layout["refl_u"])
    lo, hi = model.reflection_loss_db
    loss = np.where(refl, lo + (hi - lo) * u,
                    np.where(diff, 6.0 + (model.diffraction_max_db - 6.0) * depth / np.radians(model.diffraction_deg),
                             0.0))
    return dict(cls=cls, delay_m=delay, loss_db=loss, rate_err_mps=rate, mask_deg=np.degrees(mask))


def _hash_uniform(street: np.ndarray, col: np.ndarray, street_u: np.ndarray) -> np.ndarray:
    """A uniform [0,1) number fixed per (street, satellite column): the street's draw shifted by a
    golden-ratio multiple of the column, so that one facade reflects each satellite alike all along
    the street without an (n_streets, P) table."""
    return np.mod(street_u[street, 0] + 0.6180339887 * (col + 1), 1.0)


@dataclass
class MultipathModel:
    """Line-of-sight code multipath: amplitude ``scale_m * 10^((ref_db - cn0) / 20)`` (at most
    ``max_m``; times sqrt(chip / GPS L1 chip) for other codes), a sine of period U[``period_s``] and
    random phase per (trace, signal)."""

    scale_m: float = 1.0
    ref_db: float = 40.0
    max_m: float = 15.0
    period_s: tuple[float, float] = (5.0, 60.0)


def los_multipath(t_s: np.ndarray, cn0_db: np.ndarray, trace_of_epoch: np.ndarray, cols: np.ndarray,
                  model: MultipathModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(E,K) code error [m] and its rate [m/s] of line-of-sight multipath.

    t_s (E,) seconds since the trace's start, cn0_db (E,K), trace_of_epoch (E,) int, cols (E,K)
    satellite column of each slot.
    """
    n_tr = int(trace_of_epoch.max(initial=0)) + 1
    P = int(cols.max(initial=0)) + 1
    period = rng.uniform(*model.period_s, (n_tr, P))
    phase = rng.uniform(0, 2 * np.pi, (n_tr, P))
    amp = np.minimum(model.scale_m * 10.0 ** ((model.ref_db - cn0_db) / 20.0), model.max_m)
    w = 2 * np.pi / period[trace_of_epoch[:, None], cols]
    arg = w * t_s[:, None] + phase[trace_of_epoch[:, None], cols]
    return amp * np.sin(arg), amp * w * np.cos(arg)
