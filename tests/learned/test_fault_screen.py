"""The ``dnn`` mode's fault screen: measurements the robust WLS excluded, or that its neighbours show as
gross faults, reach neither the network nor its context WLS, and the network's guess is re-solved
without them."""
from __future__ import annotations

import numpy as np

from fusion.estimate.wls import solve_wls
from fusion.run_types import RunOptions
from fusion.trace import Trace
from learned.infer import Corrector
from learned.modes import fault_screen
from tests.estimate.test_wls_canyon import _drive
from tests.learned.test_infer import ConstantNet, _config, _noise_free


def test_dropped_measurements_do_not_reach_the_network():
    """A +200 m fault pulls the learned-weight solution; dropped, it is not asked (no sigma) and the
    solution is the truth again (noise-free ranges)."""
    tr = _noise_free(E=6, n_sats=(8, 9))
    tr.pr = tr.pr.copy()
    tr.pr[2, 0] += 200.0
    valid = np.ones(6, bool)
    corr = Corrector(ConstantNet(), _config(output="wls"))
    pulled = corr.predict(tr, tr.truth, valid)
    assert np.linalg.norm(pulled.mean_ecef[2] - tr.truth[2]) > 10.0
    drop = np.zeros(tr.mask.shape, bool)
    drop[2, 0] = True
    c = corr.predict(tr, tr.truth, valid, drop=drop)
    np.testing.assert_allclose(c.mean_ecef, tr.truth, atol=1e-3)
    assert np.isnan(c.sigma[2, 0]) and np.isfinite(c.sigma[tr.mask & ~drop]).all()
    assert c.info["meas_asked"] == pulled.info["meas_asked"] - 1
    assert c.info["meas_unseen_signal"] == 0          # a screened fault is not a signal it cannot read


def test_screen_drops_an_absorbed_fault_and_repairs_the_guess_and_context():
    """Five satellites in one epoch (eight around it): the WLS fit absorbs a +200 m fault (no exclusion,
    position tens of metres off). The screen drops it from its neighbours' prediction, the guess is re-solved to metres, and the
    context WLS leaves it out (the residual changes of that epoch and the next are not pulled)."""
    kw, rx = _drive(n_sats=8)
    kw["mask"][4, 5:] = False
    kw["pr"][4, 2] += 200.0
    tr = Trace(**kw)
    wls = solve_wls(tr)
    assert not wls.excluded.any() and np.linalg.norm(wls.pos[4] - rx[4]) > 50.0
    drop, guess = fault_screen(tr, wls, RunOptions())
    assert np.argwhere(drop).tolist() == [[4, 2]]
    # --wls-plain: the paper's baseline screens nothing
    assert not fault_screen(tr, wls, RunOptions(wls_robust=False))[0].any()
    assert np.linalg.norm(guess[4] - rx[4]) < 5.0
    np.testing.assert_array_equal(np.delete(guess, 4, 0), np.delete(wls.pos, 4, 0))
    corr = Corrector(ConstantNet(), _config(output="wls"))
    plain, screened = corr._context(tr), corr._context(tr, drop)
    assert not screened["prev_ok"][5, 2] and plain["prev_ok"][5, 2]
    other = np.ones(tr.n_epochs, bool)
    other[[4, 5]] = False
    np.testing.assert_allclose(screened["dres"][other], plain["dres"][other])
    assert np.abs(screened["dres"][[4, 5]]).max() < 5.0 < np.abs(plain["dres"][[4, 5]]).max()
    # a clean drive: nothing screened, the guess is the WLS's
    kw, _ = _drive(n_sats=8)
    kw["mask"][4, 5:] = False
    clean = Trace(**kw)
    w = solve_wls(clean)
    drop, guess = fault_screen(clean, w, RunOptions())
    assert not drop.any() and np.array_equal(guess, w.pos)
