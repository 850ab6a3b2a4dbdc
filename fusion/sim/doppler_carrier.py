"""Simulated Doppler (pseudorange rate) and carrier phase (accumulated delta range) for the slots
the simulator picked, with the truth-known arcs, ambiguities and cycle slips tests need.

Models (the ones the graph inverts; satellite clock already removed, like ``Trace.prr`` / ``adr``):

- ``prr = range_rate(sat, rx) + receiver clock drift + N(0, prr_sigma^2)``, the range rate of
  :func:`fusion.geometry.range_rate` (GTSAM's ``DopplerFactor`` model) at the true receiver velocity;
- ``adr = range + receiver clock + ambiguity + N(0, adr_sigma^2)``, the range of
  :func:`fusion.geometry.line_of_sight` (the pseudorange's), the ambiguity constant along an arc.

An arc of one satellite ends where it leaves the picked subset, where a trace segment starts, or
at a random cycle slip (probability ``slip_prob`` per satellite and epoch); each new arc starts with
a fresh ambiguity and sets ``adr_slip`` in that epoch's slot.
"""
from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from fusion.geometry import range_rate

if TYPE_CHECKING:  # the config lives with the simulator that imports this module
    from fusion.sim.config import SimConfig
    from fusion.trace import Trace


def with_drift_jumps(trace: Trace, sigma_mps: float, seed: int) -> Trace:
    """``trace`` with white noise of ``sigma_mps`` common to each epoch's Dopplers: a phone's clock drift as its
    Doppler shows it, jumping from epoch to epoch while the Dopplers agree with each other (the Pixel5's,
    :mod:`fusion.estimate.graph.drift_noise`); seeded."""
    jump = np.random.default_rng(seed).normal(0.0, sigma_mps, trace.n_epochs)
    return replace(trace, prr=np.where(trace.prr_ok, trace.prr + jump[:, None], trace.prr))


def receiver_velocity(t_ms: np.ndarray, rx: np.ndarray, seg_start: np.ndarray) -> np.ndarray:
    """(E,3) ECEF velocity [m/s] of the true track rx (E,3) at times t_ms (E,): central differences
    within each segment (seg_start (E,) bool), one-sided at its ends, 0 for one-epoch segments."""
    E = t_ms.shape[0]
    if E < 2:
        return np.zeros((E, 3))
    step = np.diff(rx, axis=0) / (np.diff(t_ms) * 1e-3)[:, None]          # (E-1,3) k -> k+1
    linked = ~seg_start[1:]                                                # k and k+1 same segment
    fwd = np.vstack([np.where(linked[:, None], step, np.nan), np.full((1, 3), np.nan)])
    bwd = np.vstack([np.full((1, 3), np.nan), np.where(linked[:, None], step, np.nan)])
    n = np.isfinite(fwd[:, :1]).astype(float) + np.isfinite(bwd[:, :1])
    return (np.nan_to_num(fwd) + np.nan_to_num(bwd)) / np.maximum(n, 1.0)


def carrier_arcs(in_view: np.ndarray, seg_start: np.ndarray, cfg: "SimConfig", rng: np.random.Generator
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per (epoch, PRN): new_arc (E,P) bool and ambiguity (E,P) [m].

    in_view (E,P) bool the PRN is among the picked slots; seg_start (E,) bool.
    A new arc starts at (re)acquisition, at a segment start or at a random slip; the ambiguity is a
    cumulative sum of the jumps drawn at arc starts, so it is constant along each arc.
    """
    E, P = in_view.shape
    prev = np.vstack([np.zeros((1, P), bool), in_view[:-1]])
    slip = rng.random((E, P)) < cfg.slip_prob
    new_arc = in_view & (~prev | seg_start[:, None] | slip)
    lo, hi = cfg.slip_jump_m
    jump = rng.uniform(lo, hi, (E, P)) * rng.choice([-1.0, 1.0], (E, P))
    return new_arc, np.cumsum(np.where(new_arc, jump, 0.0), axis=0)


def class_changed(cls: np.ndarray, mask: np.ndarray, pick: np.ndarray, P: int) -> np.ndarray:
    """(E,K) bool: the slot's satellite arrived by another path (line of sight, reflected, bent) in its previous
    epoch. cls (E,K) the canyon's classes of the slots, mask (E,K), pick (E,K) their columns of P satellites.
    A tracking loop whose signal turns reflected, or back, sees its phase jump by the paths' difference within a
    fraction of a second: it loses lock, and the receiver flags the slip."""
    E = mask.shape[0]
    by_sat = np.full((E, P), -1, np.int16)
    rows = np.broadcast_to(np.arange(E)[:, None], mask.shape)
    by_sat[rows[mask], pick[mask]] = cls[mask]
    change = np.zeros((E, P), bool)
    change[1:] = (by_sat[1:] != by_sat[:-1]) & (by_sat[1:] >= 0) & (by_sat[:-1] >= 0)
    return np.take_along_axis(change, pick, axis=1) & mask


def doppler_carrier_arrays(t_ms: np.ndarray, rx: np.ndarray, seg_start: np.ndarray, slots: dict,
                           pick: np.ndarray, P: int, cfg: "SimConfig", rng: np.random.Generator,
                           env: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Doppler and carrier slot arrays, empty when ``cfg`` asks for neither.

    t_ms (E,), rx (E,3) true track, seg_start (E,) bool; slots: the simulator's arrays so far
    ((E,K) ``sat_pos``, ``sat_vel``, ``mask``, ``range`` geometric range [m]; (E,) ``clock`` [m],
    ``clock_drift`` [m/s]); pick (E,K) column index of each slot out of P.
    env: optional extras: ``vel`` (E,3) receiver velocity when already computed, and the
    environment's (E,K) slot arrays (:mod:`fusion.sim.measurements`): ``prr_error`` (NLOS and
    multipath range-rate error) is added to the Doppler, ``prr_scale`` multiplies its noise sigma
    (C/N0), and ``nlos_delay`` lengthens the carrier path like the code's.
    Returns prr, prr_sigma, prr_ok, rx_vel (E,3), clock_drift (E,) with ``cfg.doppler``, and adr,
    adr_sigma, adr_ok, adr_slip, ambiguity with ``cfg.carrier``.
    """
    out: dict[str, np.ndarray] = {}
    mask = slots["mask"]
    env = env or {}
    if cfg.doppler:
        vel = env["vel"] if env.get("vel") is not None else receiver_velocity(t_ms, rx, seg_start)
        clock_drift = slots["clock_drift"]
        rate = range_rate(slots["sat_pos"], slots["sat_vel"], rx, vel) + env.get("prr_error", 0.0)
        sigma = cfg.prr_sigma_mps * env.get("prr_scale", np.ones(mask.shape))
        noise = rng.standard_normal(mask.shape) * sigma
        out.update(prr=rate + clock_drift[:, None] + noise, prr_sigma=np.where(mask, sigma, 1.0),
                   prr_ok=mask.copy(), rx_vel=vel, clock_drift=clock_drift)
    if cfg.carrier:
        in_view = np.zeros((mask.shape[0], P), bool)
        rows = np.broadcast_to(np.arange(mask.shape[0])[:, None], mask.shape)
        in_view[rows[mask], pick[mask]] = True
        new_arc, amb = carrier_arcs(in_view, seg_start, cfg, rng)
        ambiguity = np.take_along_axis(amb, pick, axis=1)
        noise = rng.standard_normal(mask.shape) * cfg.adr_sigma_m
        slip = np.take_along_axis(new_arc, pick, axis=1) & mask
        if cfg.slip_on_class_change and env.get("cls") is not None:
            slip |= class_changed(env["cls"], mask, pick, P)
        out.update(adr=slots["range"] + slots["clock"][:, None] + ambiguity + noise + env.get("nlos_delay", 0.0),
                   adr_sigma=np.where(mask, cfg.adr_sigma_m, 1.0), adr_ok=mask.copy(), adr_slip=slip,
                   ambiguity=np.where(mask, ambiguity, 0.0))
    return out
