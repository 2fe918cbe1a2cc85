"""Which of ``imucal calibrate``'s processes and phases bound its time: the wall time that a
fixed amount of extra CPU work costs where it is added. Prints a markdown table
(docs/performance.md).

Each round runs the command on the 1 h five-IMU log of :mod:`throughput` once as it is and
once per place below with ``--burn`` CPU seconds of busy work added there (by wrapping the
function named, from outside the package):

- the calibrating process, right after the reading child has started (``load_config``);
- the reading child, before its first batch (``ImuBatches.__iter__``);
- the calibrating process's reduction thread, at the first block of windows
  (``streaming._reduce_block``);
- the calibrating process, before the solve (``api.estimate``): the critical path itself, so
  the control (it should pay the whole of what is added).

A place whose added wall time is near the added CPU lies on the critical path; one near half
of it shares two busy cores (the wall is bound by the total CPU); one near zero has slack.
What a cut of that much work at a place would buy is about what adding it costs.

Run: ``python benchmarks/slack.py [--repeat 5] [--burn 0.3]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from phases import CALIBRATE_IN_PROCESS, run  # noqa: E402

#: The command line's run with busy work added at one place (argv[1]: the place, argv[2]:
#: the CPU seconds), its wall time printed.
BURNING_CLI = """
import functools, json, os, sys, time
start = time.perf_counter()
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as imucal's entry point, before numpy
from imucal_cli import api, cli, config, reading
from imucal_cli.core import streaming
place, seconds = sys.argv.pop(1), float(sys.argv.pop(1))  # the rest: calibrate's
def burn():
    end = time.thread_time() + seconds
    while time.thread_time() < end:
        for _ in range(10_000):
            pass
def before(module, name, once=False):
    inner = getattr(module, name)
    done = []
    @functools.wraps(inner)
    def burning(*args, **kwargs):
        if not (once and done):
            done.append(True)
            burn()
        return inner(*args, **kwargs)
    setattr(module, name, burning)
if place == "after fork":
    before(config, "load_config")
elif place == "child start":
    before(reading.ImuBatches, "__iter__")
elif place == "reduction":
    before(streaming, "_reduce_block", once=True)
elif place == "before solve":
    before(api, "estimate")
"""
BURNING_CLI += (
    CALIBRATE_IN_PROCESS
    + """
print(json.dumps({"wall": time.perf_counter() - start}))
"""
)

PLACES = {
    "none": "nothing added",
    "after fork": "calibrating process, right after the reading child starts",
    "child start": "reading child, before its first batch",
    "reduction": "calibrating process's reduction thread, first block of windows",
    "before solve": "calibrating process, before the solve (the control)",
}


def wall(place: str, burn_s: float, log: Path, config: Path, out: Path) -> float:
    args = [str(log), "-c", str(config), "-o", str(out)]
    return float(run(BURNING_CLI, place, str(burn_s), *args)["wall"])


def main() -> None:
    from throughput import build, compile_package

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--burn", type=float, default=0.3, help="CPU seconds added")
    args = parser.parse_args()
    log, config = build("1h", "mcap")
    compile_package()
    out = HERE / ".cache" / "out_slack.yaml"
    walls: dict[str, list[float]] = {place: [] for place in PLACES}
    for _ in range(args.repeat):  # interleaved, so that a slow phase of the machine hits all
        for place in PLACES:
            burn_s = 0.0 if place == "none" else args.burn
            walls[place].append(wall(place, burn_s, log, config, out))
    print(
        f"`imucal calibrate` of {log.name}, {args.burn:.2f} CPU s of busy work added at one "
        f"place, median of {args.repeat} interleaved rounds:\n"
    )
    print("| busy work added in the | wall s | added wall s (median of pairs) | added / burnt |")
    print("|---|---|---|---|")
    base = walls["none"]
    for place, label in PLACES.items():
        row = walls[place]
        added = statistics.median(w - b for w, b in zip(row, base, strict=True))
        share = "" if place == "none" else f"{added / args.burn:.2f}"
        added_text = "" if place == "none" else f"{added:+.3f}"
        print(f"| {label} | {statistics.median(row):.2f} | {added_text} | {share} |")


if __name__ == "__main__":
    main()
