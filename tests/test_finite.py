"""``dsg_gym.splat.finite``: the one-pass NaN/Inf check behind renderer input checks and the training
loops' gradient checks."""

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from dsg_gym.splat.finite import all_finite, first_nonfinite


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_first_bad_value_is_found_and_located(dtype, bad):
    t = torch.randn(7, 5, 3, dtype=dtype) * 1e30  # huge but finite values are fine
    assert first_nonfinite(t) is None and all_finite(t)
    t[4, 2, 1] = bad
    t[6, 0, 0] = bad  # a later one is not the first
    assert first_nonfinite(t) == (4, 2, 1)
    assert not all_finite(t)


def test_extremes_and_empty():
    big = torch.tensor([np.finfo(np.float32).max, -np.finfo(np.float32).max, 0.0, -0.0, 1e-45])
    assert all_finite(big)
    assert all_finite(torch.zeros(0, 3))
    assert all_finite(torch.arange(5))  # integers cannot be NaN


def test_non_contiguous_index_is_in_the_tensors_own_coordinates():
    t = torch.zeros(4, 6)
    v = t.t()  # [6, 4], not contiguous
    v[5, 1] = float("nan")
    assert not v.is_contiguous()
    assert first_nonfinite(v) == (5, 1)


def test_other_float_types_use_torchs_check():
    t = torch.ones(3, 2, dtype=torch.float16)
    assert all_finite(t)
    t[2, 1] = float("inf")
    assert first_nonfinite(t) == (2, 1)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=1, max_size=50))
def test_agrees_with_torch(values):
    t = torch.tensor(values, dtype=torch.float32)
    bad = torch.nonzero(~torch.isfinite(t))
    assert first_nonfinite(t) == (tuple(bad[0].tolist()) if len(bad) else None)
