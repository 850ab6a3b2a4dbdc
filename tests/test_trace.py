import numpy as np
import pytest

from fusion.errors import DataError
from fusion.trace import Trace, empty_trace, pack_rows


def _trace(E=3, S=4):
    kw = empty_trace(E, S, name="t")
    kw["t_ms"] = np.arange(E, dtype=np.int64) * 1000
    kw["mask"][:] = True
    kw["mask"][1, 2:] = False
    kw["pr"][:] = 2e7
    return Trace(**kw)


def test_pack_rows_scatters_without_loss():
    epoch = np.array([0, 0, 0, 1, 2, 2])
    vals = np.arange(6.0)
    out = pack_rows(epoch, 3, {"pr": vals})
    assert out["pr"].shape == (3, 3)
    np.testing.assert_array_equal(out["mask"].sum(axis=1), [3, 1, 2])
    np.testing.assert_array_equal(out["pr"][out["mask"]], vals)


def test_select_compacts_and_trims_slots():
    tr = _trace()
    sub = tr.select(np.array([1]))
    assert sub.n_epochs == 1 and sub.n_slots == 2 and sub.mask.all()


def test_shape_errors_name_the_field():
    kw = empty_trace(3, 4, name="bad")
    kw["t_ms"] = np.arange(3, dtype=np.int64)
    kw["pr"] = np.zeros((3, 5))
    with pytest.raises(DataError, match="sat_pos"):
        Trace(**kw)


def test_nan_in_used_slot_is_rejected_but_allowed_in_padding():
    kw = empty_trace(2, 2, name="nan")
    kw["t_ms"] = np.array([0, 1000])
    kw["mask"][0, 0] = True
    kw["pr"][1, 1] = np.nan  # padding: fine
    Trace(**kw)
    kw["pr"][0, 0] = np.nan
    with pytest.raises(DataError, match="pr has non-finite"):
        Trace(**kw)


def test_times_must_increase():
    kw = empty_trace(2, 1, name="dup")
    kw["t_ms"] = np.array([5, 5])
    with pytest.raises(DataError, match="strictly increasing"):
        Trace(**kw)


def test_select_carries_a_dropped_clock_reset_to_the_next_kept_epoch():
    kw = empty_trace(6, 1, name="jumps")
    kw["t_ms"] = np.arange(6, dtype=np.int64) * 1000
    kw["clock_reset"][[2, 5]] = True
    tr = Trace(**kw)
    # Epoch 2 (a jump) is dropped: the clock still jumped between kept epochs 1 and 3.
    np.testing.assert_array_equal(tr.select(np.array([0, 1, 3, 4])).clock_reset,
                                  [False, False, True, False])
    np.testing.assert_array_equal(tr.select(np.array([0, 1, 2, 5])).clock_reset,
                                  [False, False, True, True])
    assert not tr.select(np.array([3, 4])).clock_reset.any()


def test_select_with_a_wrong_length_mask_names_the_trace():
    with pytest.raises(DataError, match="t: cannot select epochs of a 3-epoch trace"):
        _trace().select(np.array([True, False]))


def _with_raw(E=5, S=3):
    from fusion.trace import Trace, empty_trace
    kw = empty_trace(E, S)
    kw["t_ms"] = np.arange(E, dtype=np.int64) * 1000
    kw["mask"][:] = True
    kw["sat_pos"][:] = 2e7
    kw["pr"][:] = 2.2e7
    f = np.ones((E, S))
    return Trace(**kw, cn0=30 * f, prr=f.copy(), prr_sigma=f.copy(), prr_ok=np.ones((E, S), bool),
                 adr=f.copy(), adr_sigma=f.copy(), adr_ok=np.ones((E, S), bool), adr_slip=np.zeros((E, S), bool))


def test_optional_raw_fields_travel_with_select_and_slips_break_across_dropped_epochs():
    tr = _with_raw()
    assert tr.has_doppler and tr.has_carrier
    sub = tr.select(np.array([0, 1, 3]))
    assert sub.prr.shape == (3, 3) and sub.cn0[0, 0] == 30
    # epoch 2 was dropped: the carrier chain between kept epochs 1 and 3 is broken
    assert sub.adr_slip.tolist() == [[False] * 3, [False] * 3, [True] * 3]


def test_optional_raw_fields_must_come_in_groups_and_be_finite_where_flagged():
    import dataclasses
    from fusion.errors import DataError
    tr = _with_raw()
    with pytest.raises(DataError, match="must be given together"):
        dataclasses.replace(tr, prr_ok=None)
    bad = tr.prr.copy()
    bad[1, 1] = np.nan
    with pytest.raises(DataError, match="non-finite values in slots flagged prr_ok"):
        dataclasses.replace(tr, prr=bad)
    ok = tr.prr_ok.copy()
    ok[1, 1] = False
    dataclasses.replace(tr, prr=bad, prr_ok=ok)     # NaN where not flagged: fine
