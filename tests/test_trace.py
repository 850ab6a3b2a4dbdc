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
