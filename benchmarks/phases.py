"""Where a lone ``imucal calibrate`` of the 1 h five-IMU log spends its time and CPU; prints
markdown tables (docs/performance.md).

Each round runs, in fresh processes and in turn:

- ``imucal calibrate`` as the command line runs it (the log read in a child process, the
  windows reduced in a worker thread, half of the sensors solved in a second child), with its
  phases timed from inside: start-up (interpreter, imports, the config), the stream (reading
  and the windows), the solve, the document; and the CPU seconds of the calibrating process
  and of its children;
- the same calibration in one process, as the Python API runs it (``calibrate_log``): its CPU
  seconds are the work itself, which no use of the second core can go below.

and then one more run of the command as a user runs it, with the machine's busy cores sampled
every 0.1 s from ``/proc/stat`` (Linux; on an otherwise idle machine): where the second core
idles.

The log is ``throughput.py``'s (built once, cached). Run: ``python benchmarks/phases.py
[--repeat 5]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

#: ``imucal calibrate ARGS`` (``sys.argv[1:]``) run in this process, as its entry point runs
#: it, with ``cli`` imported: the end of a script that times it from inside.
CALIBRATE_IN_PROCESS = """
def stay(code):  # the command ends the process at once (cli.leave): here it returns instead
    raise SystemExit(code)
cli.leave = stay
sys.argv = ["imucal", "calibrate", *sys.argv[1:], "-q"]
try:
    cli.main()
except SystemExit:
    pass
"""

#: The command line's run, its phases marked by wrapping the pipeline's steps.
TIMED_CLI = (
    """
import json, os, resource, sys, time
start = time.perf_counter()
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as imucal's entry point, before numpy
marks = {}
from imucal_cli import cli, pipeline, api
def wrap(module, name, label):
    inner = getattr(module, name)
    def timed(*args, **kwargs):
        marks.setdefault(label + " start", time.perf_counter() - start)
        out = inner(*args, **kwargs)
        marks[label + " end"] = time.perf_counter() - start
        return out
    setattr(module, name, timed)
wrap(pipeline, "read_log", "stream")
wrap(api, "estimate", "solve")
"""
    + CALIBRATE_IN_PROCESS
    + """marks["end"] = time.perf_counter() - start
own, children = (resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
marks["cpu calibrating"] = own.ru_utime + own.ru_stime
marks["cpu children"] = children.ru_utime + children.ru_stime
print(json.dumps(marks))
"""
)

#: The Python API's run, in one process.
ONE_PROCESS = """
import json, os, resource, sys, time
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the command line runs
start = time.perf_counter()
from imucal_cli.api import calibrate_log
calibrate_log(sys.argv[1], sys.argv[3])
own = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({"end": time.perf_counter() - start, "cpu": own.ru_utime + own.ru_stime}))
"""


def run(code: str, *args: str) -> dict[str, float]:
    # from the cache folder: from a checkout, `python -c` would import the checkout's code
    # whatever PYTHONPATH names (to time another tree: PYTHONPATH=TREE python phases.py)
    out = subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        check=True,
        cwd=HERE / ".cache",
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def busy_jiffies() -> tuple[int, int]:
    """The machine's CPU time so far, busy and in all (``/proc/stat``'s first line)."""
    with open("/proc/stat") as stat:
        fields = [int(x) for x in stat.readline().split()[1:]]
    return sum(fields) - fields[3] - fields[4], sum(fields)  # less idle and iowait


def cores_busy(args: list[str], step_s: float = 0.1) -> list[tuple[float, float]]:
    """``imucal calibrate ARGS`` in a fresh process, and per ``step_s`` from its start the
    cores busy (all of the machine's, ``os.cpu_count()`` at most)."""
    import os
    import time

    command = [sys.executable, "-m", "imucal_cli.cli", "calibrate", *args, "-q"]
    process = subprocess.Popen(command, cwd=HERE / ".cache")
    start, last, samples = time.perf_counter(), busy_jiffies(), []
    while process.poll() is None:
        time.sleep(step_s)
        now = busy_jiffies()
        share = (now[0] - last[0]) / max(now[1] - last[1], 1)
        samples.append((time.perf_counter() - start, share * (os.cpu_count() or 1)))
        last = now
    return samples


def main() -> None:
    from throughput import build, compile_package

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    log, config = build("1h", "mcap")
    compile_package()
    out = HERE / ".cache" / "out_phases.yaml"
    cli_runs, api_runs = [], []
    for _ in range(args.repeat):
        cli_runs.append(run(TIMED_CLI, str(log), "-c", str(config), "-o", str(out)))
        api_runs.append(run(ONE_PROCESS, str(log), "-c", str(config)))

    def median(values: list[float]) -> str:
        return f"{statistics.median(values):.2f}"

    phases = {
        "start-up (interpreter, imports, config)": [r["stream start"] for r in cli_runs],
        "stream (reading, windows)": [r["stream end"] - r["stream start"] for r in cli_runs],
        "solve": [r["solve end"] - r["solve start"] for r in cli_runs],
        "document and exit": [r["end"] - r["solve end"] for r in cli_runs],
        "whole command": [r["end"] for r in cli_runs],
    }
    print(f"`imucal calibrate` of {log.name}, median of {args.repeat} runs:\n")
    print("| phase | wall s |\n|---|---|")
    for name, values in phases.items():
        print(f"| {name} | {median(values)} |")
    cpu = [r["cpu calibrating"] + r["cpu children"] for r in cli_runs]
    print("\n| CPU s | median | min | max |\n|---|---|---|---|")
    rows = {
        "calibrating process": [r["cpu calibrating"] for r in cli_runs],
        "its children (reading, half the solves)": [r["cpu children"] for r in cli_runs],
        "the command, all processes": cpu,
        "one process (`calibrate_log`): the work itself": [r["cpu"] for r in api_runs],
    }
    for name, values in rows.items():
        print(f"| {name} | {median(values)} | {min(values):.2f} | {max(values):.2f} |")
    work = statistics.median(r["cpu"] for r in api_runs)
    print(
        f"\nIn one process the calibration took {median([r['end'] for r in api_runs])} s of "
        f"wall time. On two cores no schedule of that work takes less than half its CPU: "
        f"{work / 2:.2f} s."
    )
    samples = cores_busy([str(log), "-c", str(config), "-o", str(out)])
    print("\nOne more run of the command, the cores busy every 0.1 s:\n")
    print("| s | cores busy |\n|---|---|")
    previous = 0.0
    for end_s, busy in samples:
        print(f"| {previous:.2f}-{end_s:.2f} | {busy:.1f} |")
        previous = end_s


if __name__ == "__main__":
    main()
