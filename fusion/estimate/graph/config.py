"""Settings of the fused graph: pseudorange noise, robust losses, motion and clock models, the
learned prior's use, solver tolerances."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass
class GraphConfig:
    """Noise and robustness settings of the fused graph.

    Defaults were tuned on training traces only (2020-05-14-US-MTV-1, 2020-06-05-US-MTV-1,
    2020-09-04-US-SF-2); the tables, and the command that reprints them, are in
    ``experiments/results/graph_tuning.md``.
    """

    # Pseudorange sigma [m]: sqrt((pr_sigma_scale * pr_sigma)^2 + (pr_sigma_zenith_m / sin(el))^2).
    pr_sigma_scale: float = 1.0
    pr_sigma_zenith_m: float = 1.0
    # A slot-noise provider's sigmas (the learned per-satellite head): "absolute" = used as given;
    # "relative" = rescaled per epoch so that their median over the epoch's satellites equals the
    # median of the sigma model above (the provider reweights satellites against each other, the
    # graph keeps the level at which its motion and clock models were tuned).
    slot_noise_level: str = "relative"
    robust: str = "cauchy"             # "huber", "cauchy" or "none"
    robust_k: float = 2.0              # scale on the whitened residual
    # Motion: "rw" = zero-mean position random walk; "cv" = velocity states, constant velocity.
    motion: str = "cv"
    # rw: per-axis position step sigma per second [m/s] (horizontal / vertical, NED at the epoch).
    rw_sigma_h_mps: float = 10.0
    rw_sigma_v_mps: float = 2.0
    # cv: velocity random walk [m/s per sqrt(s)] horizontal / vertical; position process noise
    # [m per sqrt(s)] on p_k = p_{k-1} + v_{k-1} dt.
    cv_accel_h: float = 1.0
    cv_accel_v: float = 0.2
    cv_pos_sigma_m: float = 0.5
    max_gap_s: float = 10.0            # motion chain broken beyond this epoch gap
    # Clock random walk around the WLS-derived drift: sigma = clock_sigma_m + clock_rw_m * sqrt(dt).
    clock_sigma_m: float = 2.0
    clock_rw_m: float = 5.0
    clock_jump_m: float = 1000.0       # WLS clock step beyond drift larger than this = clock reset
    drift_window: int = 5              # epochs each side for the robust WLS clock-drift estimate
    # Learned prior: covariance used = prior_cov_scale * cov + prior_sigma_floor_m^2 * I.
    # Where the provider is asked: "graph" = at the solution of the same graph without the prior
    # (a better guess than WLS, around which the network was trained: on a held-out training trace
    # this beat asking at WLS, experiments/results/graph_tuning.md); "wls" = at the WLS positions (one solve
    # instead of two).
    # Incremental mode uses the no-prior smoother's *online* estimates, so it stays causal.
    prior_at: str = "graph"
    prior_cov_scale: float = 1.0
    prior_sigma_floor_m: float = 2.0
    # robust loss on the prior's Mahalanobis distance (in sigmas), so that a wrong network output
    # cannot drag the solution: "huber", "cauchy", "none"
    prior_robust: str = "cauchy"
    prior_robust_k: float = 1.0
    # Batch solver: LM stops when the cost improves by less than this fraction (1e-6 took 2-4x the
    # iterations for < 1 cm change on the training traces).
    lm_rel_tol: float = 1e-4
    lm_max_iter: int = 50
    # Incremental (ISAM2): relinearisation threshold and extra update() calls after the last epoch.
    isam_relin_threshold: float = 0.05
    isam_settle: int = 2
    # relinearisation checked every 5th update: 2.5x faster than every update, same accuracy on the
    # training traces
    isam_relin_skip: int = 5
    # ISAM2 stops back-substitution below this change. GTSAM has one threshold for all variables,
    # so it is applied in clock units (isam_wildfire_m / c seconds), i.e. effectively full
    # propagation for positions (see benchmarks/bench_graph.py for the ms/epoch this costs).
    isam_wildfire_m: float = 0.001
    # Inter-system biases: "window" = one constant bias per non-reference signal (GLONASS G1,
    # Galileo E1, BeiDou B1I, ... vs GPS L1) per motion component; "none" = one clock for all.
    # The zero-mean prior sigma was chosen a priori, not tuned: the derived files' isrbM already
    # removes the bulk of the bias, the residue is metres, and 10 m leaves it free while keeping a
    # group seen by a single satellite determinable. GPS-only traces get no bias states at all.
    isb: str = "window"
    isb_sigma_m: float = 10.0
    # Doppler and carrier phase, used where the trace carries them (RunOptions.use_doppler /
    # use_carrier). Chosen a priori from the phones' reported sigmas and checked on simulated traces
    # only (experiments/doppler_carrier.py), not tuned on real data:
    # Doppler sigma [m/s] = sqrt((prr_sigma_scale * prr_sigma)^2 + prr_sigma_floor_mps^2).
    prr_sigma_scale: float = 1.0
    prr_sigma_floor_mps: float = 0.05
    # Time-differenced carrier sigma [m] = sqrt(adr_sigma(k-1)^2 + adr_sigma(k)^2 + tdcp_sigma_floor_m^2):
    # the floor covers what differencing leaves (multipath change, iono change over a second).
    tdcp_sigma_floor_m: float = 0.02
    # Clock with a drift state (graphs with Doppler): c(k) = c(j) + drift(j) * dt + w, w ~ N(0, rw^2 dt),
    # and drift(k) - drift(j) ~ N(0, drift_rw_mps^2 dt); a loose prior starts each chain.
    drift_clock_rw_m: float = 1.0
    drift_rw_mps: float = 0.2
    drift_start_sigma_mps: float = 1000.0
    # Where the carrier factors are linearised (they keep that point, see factors.tdcp_factor_uqq):
    # "graph" = the solution of the same graph without carrier (its online estimates in incremental
    # mode), "initial" = the WLS track. The factor's linearisation error grows with the distance of
    # that point from the solution (~1e-4 of it per second), so "graph" guards against WLS outliers
    # for one more, carrier-free (fast) solve; on the simulated benchmark trace (WLS good to ~11 m)
    # the two differ by only 4 mm at p50 (benchmarks/doppler_carrier_speed.py).
    tdcp_linearize_at: str = "graph"
    # Vehicle odometry (RunOptions.use_odometry; fusion.estimate.graph.odometry), chosen a priori, not
    # tuned: speed sigma floor [m/s] under the file's variance (wheel speed quantisation, slip); heading
    # sigma per step [rad] beyond the fitted offset and gyro drift (1.7 deg: the file's turn-rate noise,
    # 0.002 rad/s, integrated over minutes, doubled); pitch [rad] for slopes the body frame hides (5 %);
    # priors on the heading state's offset [rad] and gyro bias [rad/s] around the fit to the WLS track.
    odom_speed_sigma_floor_mps: float = 0.1
    odom_heading_sigma_rad: float = 0.03
    odom_pitch_sigma_rad: float = 0.05
    odom_heading_prior_rad: float = 0.2
    odom_gyro_bias_prior_radps: float = 0.002
