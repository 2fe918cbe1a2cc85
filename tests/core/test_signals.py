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


def test_lowpass_with_a_second_cutoff_is_the_two_filters_in_turn():
    """Two zero-phase responses multiplied in one pass equal the two filters applied one after
    the other (to round-off, away from the ends), and the pass band is kept."""
    from imucal_cli.core.signals import Lowpass

    rng = np.random.default_rng(6)
    x = np.cumsum(rng.normal(size=(4000, 2)), axis=0)
    both = Lowpass(5.0, 200.0, 4, 40.0)(x)
    in_turn = Lowpass(5.0, 200.0)(Lowpass(40.0, 200.0)(x))
    np.testing.assert_allclose(
        both[200:-200], in_turn[200:-200], rtol=0, atol=1e-9 * np.abs(x).max()
    )
    t = np.arange(4000) / 200.0
    slow = np.sin(2 * np.pi * 0.2 * t)
    np.testing.assert_allclose(
        Lowpass(5.0, 200.0, 4, 40.0)(slow)[200:-200], slow[200:-200], atol=1e-6
    )
