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


@pytest.mark.parametrize(("n", "step"), [(4000, 2), (3001, 2), (2999, 4), (50, 2)])
def test_lowpass_decimated_is_every_step_th_sample(n, step):
    """Kept every ``step``-th sample, the low-pass gives what the full filter gives there: to
    its response at the new Nyquist frequency (white noise in, the worst case, and a smooth
    signal, whose only content there is what the transform's wrap-around leaves)."""
    from imucal_cli.core.resample import ALIAS_GAIN
    from imucal_cli.core.resample import decimation as _decimation
    from imucal_cli.core.signals import Lowpass

    lowpass = Lowpass(5.0, 200.0 * step / 2, 4, 40.0 * step / 2)
    assert _decimation(lowpass, 100.0) == step
    rng = np.random.default_rng(n)
    noise = rng.normal(size=(n, 3))
    full, kept = lowpass(noise), lowpass(noise, step)
    assert kept.shape == full[::step].shape
    np.testing.assert_allclose(kept, full[::step], rtol=0, atol=10 * ALIAS_GAIN)
    t = np.arange(n) / lowpass.rate_hz
    slow = np.stack([np.sin(2 * np.pi * 0.7 * t), 0.3 * t + np.cos(2 * np.pi * 1.9 * t)], 1)
    np.testing.assert_allclose(
        lowpass(slow, step), lowpass(slow)[::step], rtol=0, atol=10 * ALIAS_GAIN
    )


def test_no_decimation_where_the_response_would_alias():
    """A low-pass that passes content near the new Nyquist frequency is not decimated."""
    from imucal_cli.core.resample import decimation as _decimation
    from imucal_cli.core.signals import Lowpass

    assert _decimation(Lowpass(20.0, 200.0, 4, 40.0), 100.0) == 1
    assert _decimation(Lowpass(5.0, 150.0, 4, 40.0), 100.0) == 1


def test_a_triad_saturates_where_its_largest_reading_repeats_at_a_full_scale():
    """An int16 gyro at 2000 deg/s clips at -32768 and +32767 counts (3e-5 apart): readings at
    either end count as at its full scale; a peak reached once, or readings repeating below the
    narrowest full scale sold (125 deg/s), do not saturate."""
    from imucal_cli.core.signals import MIN_FULL_SCALE, FullScale

    count = np.radians(2000.0) / 32768
    rng = np.random.default_rng(0)
    values = rng.normal(0.0, 5.0, (1000, 3))
    values[[10, 500, 900], [0, 1, 2]] = [-32768 * count, 32767 * count, 32767 * count]
    triad = FullScale()
    for part in np.array_split(np.arange(1000), 7):  # in batches, as messages come
        triad.add(part * 1000, values[part])
    assert triad.saturated(1.0, MIN_FULL_SCALE[0])
    assert triad.readings == 3
    assert triad.after(0).tolist() == [10_000, 500_000, 900_000]
    assert triad.after(600_000).tolist() == [900_000]  # and the earlier ones are forgotten
    assert triad.after(0).tolist() == [900_000]

    peak = FullScale()
    peak.add(
        np.arange(1000), values[:, :1] * 0.1 + np.where(np.arange(1000) == 7, 30.0, 0.0)[:, None]
    )
    assert not peak.saturated(1.0, MIN_FULL_SCALE[0])

    slow = FullScale()  # a steady turn at 1 rad/s, quantised: its top repeats, but is no range
    slow.add(np.arange(1000), np.round(np.full((1000, 3), 1.0) + rng.normal(0, 1e-3, (1000, 3)), 2))
    assert slow.readings >= 3 and not slow.saturated(1.0, MIN_FULL_SCALE[0])


def test_near_tells_the_query_times_within_a_margin_of_a_stamp():
    from imucal_cli.core.signals import near

    stamps = np.array([1.0, 5.0])
    query = np.array([0.0, 0.49, 0.5, 1.2, 3.0, 4.6, 5.5, 6.0])
    assert near(query, stamps, 0.5).tolist() == [False, False, True, True, False, True, True, False]
    assert not near(query, np.zeros(0), 1.0).any()


def test_a_rate_held_at_its_top_is_no_saturation():
    """A wheel rolling at a steady speed holds its largest rate for seconds: readings repeat at
    the top to the noise (each a new value), spread alike into the band below. That is the
    motion, not a clipped axis (its windows were dropped as saturated)."""
    from imucal_cli.core.signals import MIN_FULL_SCALE, FullScale

    rng = np.random.default_rng(1)
    rate = 23.0 + 1e-4 * rng.normal(size=(2000, 1))  # a steady 1,318 deg/s, a tactical gyro
    held = FullScale()
    held.add(np.arange(2000), np.hstack([rate, np.zeros((2000, 2))]))
    assert held.readings >= 3 and not held.saturated(1.0, MIN_FULL_SCALE[0])
    mems = 23.0 + 0.005 * rng.normal(size=(2000, 1))  # a MEMS gyro's, its top clipped
    clipped = FullScale()
    clipped.add(np.arange(2000), np.hstack([np.minimum(mems, 23.001), np.zeros((2000, 2))]))
    assert clipped.saturated(1.0, MIN_FULL_SCALE[0])


def test_lowpass_results_are_their_own_whatever_filters_after_them():
    """The low-pass works in buffers of its thread's, kept from call to call: a result is not
    one of them (a longer signal filtered after it leaves it as it was), and threads filtering
    at once each get what filtering alone gives."""
    from concurrent.futures import ThreadPoolExecutor

    from imucal_cli.core.signals import Lowpass

    rng = np.random.default_rng(11)
    lowpass = Lowpass(5.0, 200.0, 4, 40.0)
    signals = [rng.normal(size=(n, 6)) for n in (3000, 9000, 2000, 9000, 5000, 3000)]
    alone = [lowpass(x, 2).copy() for x in signals]
    first = lowpass(signals[0], 2)
    lowpass(signals[1])  # a longer one, undecimated: every buffer used again, grown
    assert np.array_equal(first, alone[0])
    with ThreadPoolExecutor(3) as pool:
        for _ in range(3):
            together = list(pool.map(lambda x: lowpass(x, 2), signals))
            assert all(np.array_equal(a, b) for a, b in zip(together, alone, strict=True))
