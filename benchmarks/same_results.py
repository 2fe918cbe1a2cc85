"""Whether two versions of the package give the same results on the accuracy cases; prints a
table.

For a change meant not to alter results (a faster contraction, a reordered solve): every case
of ``accuracy.py`` the simulator makes (not the mistakes of a config or a ``/tf_static``, which
``accuracy.py`` reads from files) for ``--seeds`` seeds is calibrated by this checkout's
package and by the one under ``--against`` (a tree holding ``imucal_cli/``, e.g. ``git
worktree add /tmp/old REV``, run in a child process with that tree first on its path), and per
case it prints the statuses that differ and the largest relative difference over every
sensor's estimate (translation, rotation vector, clock offset) and its total and statistical
std.

Run: ``python benchmarks/same_results.py --against TREE [--seeds 2] [--cases urban/none ...]``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from accuracy import CASES, MISTAKES

HERE = Path(__file__).resolve().parent


def figures(scenario: str, errors: str, seed: int) -> dict[str, dict]:
    """Per sensor: the status, and every estimated figure as one flat list."""
    from imucal_cli.api import calibrate_streams
    from imucal_cli.sim import DriveOptions, simulate_drive, with_errors

    drive = simulate_drive(
        with_errors(DriveOptions(scenario=scenario, seed=seed, sensors=4), errors)
    )
    result = calibrate_streams(drive.streams(), drive.config())
    out = {}
    for name, estimate in result.estimates.items():
        T = estimate.T_base_imu
        values = [*T.translation, *T.rotation.as_rotvec(), estimate.time_offset_s]
        for cov in (estimate.covariance, estimate.statistical_covariance):
            values += [] if cov is None else np.sqrt(np.diag(cov)).tolist()
        out[name] = {"status": estimate.status, "values": [float(v) for v in values]}
    return out


def run_all(cases: list[tuple[str, str]], seeds: int) -> dict[str, dict]:
    return {
        f"{scenario}/{errors}/{seed}": figures(scenario, errors, seed)
        for scenario, errors in cases
        for seed in range(seeds)
    }


def relative(a: list[float], b: list[float]) -> float:
    if len(a) != len(b):
        return float("inf")
    x, y = np.asarray(a), np.asarray(b)
    scale = np.maximum(np.maximum(np.abs(x), np.abs(y)), 1e-300)
    return float(np.max(np.abs(x - y) / scale)) if len(x) else 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", type=Path)
    parser.add_argument("--seeds", type=int, default=2)
    # (the mistakes' cases are a config and a /tf_static read from a file: accuracy.py's own)
    simulated = [f"{s}/{e}" for s, e in CASES if e not in MISTAKES]
    parser.add_argument("--cases", nargs="*", default=simulated, choices=simulated)
    parser.add_argument("--dump", type=Path, help=argparse.SUPPRESS)  # the child's answer
    args = parser.parse_args()
    cases = [tuple(c.split("/")) for c in args.cases]
    if args.dump is not None:
        args.dump.write_text(json.dumps(run_all(cases, args.seeds)))
        return
    if args.against is None or not (args.against / "imucal_cli").is_dir():
        raise SystemExit("--against TREE: a folder holding the other version's imucal_cli/")
    with tempfile.TemporaryDirectory() as tmp:
        dump = Path(tmp) / "other.json"
        env = os.environ | {"PYTHONPATH": f"{args.against}{os.pathsep}{HERE}"}
        command = [sys.executable, __file__, "--seeds", str(args.seeds), "--dump", str(dump)]
        subprocess.run([*command, "--cases", *args.cases], env=env, check=True, cwd=tmp)
        other = json.loads(dump.read_text())
    mine = run_all(cases, args.seeds)
    print("| case | sensors | statuses differing | largest relative difference |")
    print("|---|---|---|---|")
    worst = 0.0
    for scenario, errors in cases:
        keys = [k for k in mine if k.startswith(f"{scenario}/{errors}/")]
        pairs = [(mine[k][n], other[k][n]) for k in keys for n in mine[k]]
        differ = sum(a["status"] != b["status"] for a, b in pairs)
        largest = max(relative(a["values"], b["values"]) for a, b in pairs)
        worst = max(worst, largest)
        print(f"| {scenario}/{errors} | {len(pairs)} | {differ} | {largest:.1e} |")
    print(f"\nlargest relative difference over every case: {worst:.1e}")


if __name__ == "__main__":
    main()
