"""Signal helpers (core/signals.py) against the libraries they stand in for."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import welch as scipy_welch

from imucal_cli.core.signals import welch


@pytest.mark.parametrize(("n", "nperseg"), [(5000, 512), (4097, 256), (1000, 1000), (2048, 33)])
def test_welch_is_scipys(n, nperseg):
    rng = np.random.default_rng(n)
    x = rng.normal(size=(n, 3)).cumsum(axis=0) * 0.01 + rng.normal(size=(n, 3))
    f_ref, p_ref = scipy_welch(x, fs=200.0, nperseg=nperseg, axis=0)
    f, p = welch(x, 200.0, nperseg)
    assert np.array_equal(f, f_ref)
    np.testing.assert_allclose(p, p_ref, rtol=1e-12, atol=1e-15 * np.abs(p_ref).max())
