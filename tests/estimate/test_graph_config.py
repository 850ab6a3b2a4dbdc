"""--graph-config FILE.toml: every GraphConfig field from a file, flags on top, one-line errors."""
from __future__ import annotations

import pytest

from fusion.errors import ConfigError, GeometryError
from fusion.estimate.graph.config import GraphConfig, graph_config_toml, load_graph_config


def test_a_file_sets_fields_and_round_trips(tmp_path):
    f = tmp_path / "g.toml"
    f.write_text('robust_k = 3\nmotion = "rw"\nuse_doppler = false\n')
    cfg = load_graph_config(f)
    assert cfg.robust_k == 3.0 and isinstance(cfg.robust_k, float) and cfg.motion == "rw" and not cfg.use_doppler
    assert cfg.isb == GraphConfig().isb                                   # the rest: defaults
    f.write_text(graph_config_toml(cfg))
    assert load_graph_config(f) == cfg
    f.write_text('[graph]\nmax_gap_s = 4.0\n')
    assert load_graph_config(f).max_gap_s == 4.0
    f.write_text('robust_k = 3.0\n[graph]\nmotion = "rw"\n')      # robust_k was dropped without a word
    with pytest.raises(ConfigError, match=r"both outside and inside the \[graph\] table \('robust_k' outside\)"):
        load_graph_config(f)


@pytest.mark.parametrize("text, says", [('robust_kk = 3.0\n', "unknown graph setting 'robust_kk'"),
                                        ('robust_k = "big"\n', "'robust_k' must be a number"),
                                        ('use_doppler = 1\n', "'use_doppler' must be true or false"),
                                        ('lm_max_iter = 2.5\n', "'lm_max_iter' must be a whole number"),
                                        ('robust_k = \n', "not a TOML file"),
                                        ('robust_k = -1.0\n', "'robust_k' must be a finite number > 0"),
                                        ('lm_max_iter = 0\n', "'lm_max_iter' must be a finite number > 0"),
                                        ('max_gap_s = nan\n', "'max_gap_s' must be a finite number > 0"),
                                        ('prior_sigma_floor_m = -2.0\n', "must be a finite number >= 0"),
                                        ('motion = "rwx"\n', "'motion' must be one of 'cv', 'rw', got 'rwx'"),
                                        ('clock_drift_states = "yes"\n', "'clock_drift_states' must be one of"),
                                        ('batch_solver = "lu"\n', "'batch_solver' must be one of"),
                                        ('unlearned_robust = "tukey"\n', "'unlearned_robust' must be one of"),
                                        ('learned_robust = "tukey"\n', "'learned_robust' must be one of")])
def test_bad_files_name_the_file_and_the_setting(tmp_path, text, says):
    f = tmp_path / "g.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=says) as exc:
        load_graph_config(f)
    assert str(f) in str(exc.value) and "\n" not in str(exc.value)
    with pytest.raises(ConfigError, match="cannot read"):
        load_graph_config(tmp_path / "missing.toml")


def test_a_zero_floor_is_allowed(tmp_path):
    f = tmp_path / "g.toml"
    f.write_text("prior_sigma_floor_m = 0.0\nprr_cn0_ref_dbhz = 0.0\n")
    assert load_graph_config(f).prr_cn0_ref_dbhz == 0.0


def test_flags_override_the_file(tmp_path):
    from tests.run_options import parse_run_options

    f = tmp_path / "g.toml"
    f.write_text("use_carrier = true\nincremental = false\nrobust_k = 4.0\n")
    opts = parse_run_options(["--graph-config", str(f), "--no-carrier", "--incremental"])
    assert opts.graph.robust_k == 4.0 and not opts.use_carrier and opts.incremental and opts.use_doppler


def test_every_string_setting_has_its_choices_and_the_defaults_pass():
    from dataclasses import fields

    from fusion.estimate.graph.config import CHOICES, check_choices

    assert {f.name for f in fields(GraphConfig) if f.type == "str"} == set(CHOICES)
    check_choices(GraphConfig(), "defaults")


def test_clock_settings_without_effect_are_said(tmp_path):
    """clock_sigma_m / clock_rw_m only act on graphs without drift states: set with the default "always",
    the file is loaded with a warning saying so; with "doppler" they act, and nothing is said."""
    import warnings

    f = tmp_path / "g.toml"
    f.write_text("clock_rw_m = 500.0\n")
    with pytest.warns(UserWarning, match="clock_rw_m act only without clock-drift states"):
        assert load_graph_config(f).clock_rw_m == 500.0
    f.write_text('clock_rw_m = 500.0\nclock_drift_states = "doppler"\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_graph_config(f)


@pytest.mark.parametrize("setting, said", [("robust_k", "error is not finite at its start"),
                                           ("cv_accel_h", "noise covariance of the graph .* is not positive definite")])
def test_settings_no_float_can_hold_are_a_one_line_error_not_the_wls_track(shipped_trace_dir, setting, said):
    """A sigma of 1e-300 made the graph's error NaN (GTSAM then left the WLS track, written as the graph's) or
    its Cholesky fail deep in numpy: now a GeometryError saying what is wrong."""
    from fusion.modes import run_modes
    from fusion.prepare.load import load_trace
    from fusion.run_types import RunOptions

    tr = load_trace(shipped_trace_dir)
    with pytest.raises(GeometryError, match=said):
        run_modes(tr, ["fused-nodnn"], RunOptions(graph=GraphConfig(**{setting: 1e-300})))
