"""The package's own kernels against the library code they stand in for; prints a markdown table
(docs/performance.md). Each row is CPU time (``time.process_time``), the least of ``--repeat``
rounds of many calls, and the largest difference of the two results:

- the natural cubic spline (``core.resample.NaturalCubic``: one LAPACK ``ptsv`` and a
  two-point evaluation) against ``scipy.interpolate.CubicSpline(bc_type="natural")``, on a
  block of a 200 Hz IMU (60 s and its padding, six columns) evaluated with two derivatives on
  the 100 Hz grid;
- the symmetric products ``[a]x[b]x + [b]x[a]x`` of the base's terms (``core.moments.
  upper_symmetric_products``, element by element) against ``einsum`` of the (n, 3, 3) stacks;
- the low-pass's real transforms through ``numpy.fft`` against ``scipy.fft`` (both pocketfft);
- MCAP chunks read, decoded and calibrated in groups of ``GROUP_BYTES`` against one chunk at a
  time (``imucal_cli.calibrate`` of the 1 h log of :mod:`throughput`, built there and cached).

Run: ``python benchmarks/kernels.py [--repeat 5]``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def least(function, calls: int, repeat: int) -> float:
    """CPU seconds of one call: the least over ``repeat`` rounds of ``calls`` calls."""
    best = np.inf
    for _ in range(repeat):
        start = time.process_time()
        for _ in range(calls):
            function()
        best = min(best, (time.process_time() - start) / calls)
    return best


def spline_row(repeat: int) -> tuple[str, float, float, float]:
    from scipy.interpolate import CubicSpline

    from imucal_cli.core.resample import NaturalCubic

    rng = np.random.default_rng(0)
    t = np.cumsum(np.full(12800, 0.005) + 1e-6 * rng.random(12800))
    y = rng.standard_normal((len(t), 6))
    query = np.linspace(t[400], t[-400], 6000)

    def own():
        return NaturalCubic(t, y).derivatives(query, 2)

    def scipy():
        spline = CubicSpline(t, y, bc_type="natural")
        return [spline(query), spline(query, 1), spline(query, 2)]

    scale = [np.abs(a).max() for a in scipy()]
    difference = max(np.abs(a - b).max() / s for a, b, s in zip(own(), scipy(), scale, strict=True))
    return (
        "natural cubic spline, 12,800 knots x 6, 3 derivatives at 6,000 points",
        least(own, 20, repeat),
        least(scipy, 20, repeat),
        difference,
    )


def products_row(repeat: int) -> tuple[str, float, float, float]:
    from imucal_cli.core.moments import upper_symmetric_products

    rng = np.random.default_rng(1)
    a, b = rng.standard_normal((6600, 3)), rng.standard_normal((6600, 3))
    out = np.empty((6600, 6))
    upper = np.triu_indices(3)

    def own():
        upper_symmetric_products(a, b, out)
        return out

    def einsum():
        m = np.einsum("ni,nj->nij", a, b)
        m = m + m.transpose(0, 2, 1)
        m[:, [0, 1, 2], [0, 1, 2]] -= 2.0 * np.einsum("ni,ni->n", a, b)[:, None]
        return m[:, upper[0], upper[1]]

    difference = float(np.abs(own() - einsum()).max())
    return (
        "symmetric products of a block, 6,600 x 3",
        least(own, 200, repeat),
        least(einsum, 200, repeat),
        difference,
    )


def fft_row(repeat: int) -> tuple[str, float, float, float]:
    """The low-pass's transforms as ``core.signals.Lowpass`` makes them (numpy's pocketfft,
    the decimated inverse) against scipy's, on the base's 33 terms of a block."""
    from scipy import fft

    x = np.random.default_rng(2).standard_normal((33, 7200))

    def own():
        return np.fft.irfft(np.fft.rfft(x, axis=1)[:, :1801], n=3600, axis=1)

    def library():
        return fft.irfft(fft.rfft(x, axis=1)[:, :1801], n=3600, axis=1)

    difference = float(np.abs(own() - library()).max())
    return (
        "the low-pass's transforms of a block, 33 x 7,200 (numpy.fft / scipy.fft)",
        least(own, 100, repeat),
        least(library, 100, repeat),
        difference,
    )


def groups_row(repeat: int) -> tuple[str, float, float, float]:
    sys.path.insert(0, str(HERE))
    from throughput import build

    import imucal_cli
    from imucal_cli.io import mcap_log

    log, config = build("1h", "mcap")
    grouped = mcap_log.GROUP_BYTES
    found = {}

    def calibrate(group_bytes: int) -> None:
        mcap_log.GROUP_BYTES = group_bytes
        try:
            cal = imucal_cli.calibrate(log, config)
        finally:
            mcap_log.GROUP_BYTES = grouped
        found[group_bytes] = np.array(
            [cal.T_base_lidar(n).as_matrix() for n in sorted(cal.estimates)]
        )

    own, other = (
        least(lambda: calibrate(grouped), 1, repeat),
        least(lambda: calibrate(1), 1, repeat),
    )
    return (
        f"the 1 h MCAP calibrated: chunks in groups of {grouped >> 20} MiB / one at a time",
        own,
        other,
        float(np.abs(found[grouped] - found[1]).max()),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    print("| kernel | own CPU ms | library CPU ms | own / library | largest difference |")
    print("|---|---|---|---|---|")
    for row in (spline_row, products_row, fft_row, groups_row):
        name, own, other, difference = row(args.repeat)
        print(
            f"| {name} | {own * 1e3:.3f} | {other * 1e3:.3f} | {own / other:.2f} | "
            f"{difference:.2g} |"
        )


if __name__ == "__main__":
    main()
