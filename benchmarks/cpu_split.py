"""Where the CPU of one calibration goes, against the floor; prints a markdown table
(docs/performance.md).

On the 1 h five-IMU MCAP of :mod:`throughput` (built there and cached), each step's CPU seconds
(``time.process_time``; the interpreter's start as user + system of a fresh process):

- the interpreter's start (``python -c pass``), then in a fresh process the libraries' imports
  (numpy, scipy's linear algebra, special functions and rotations, typer, rich, PyYAML, mcap,
  zstandard: what ``calibrate`` imports), then imucal's own modules beyond those;
- in one process, ``imucal_cli.calibrate`` with the functions of each step timed where the
  pipeline calls them (wrapped for the measurement, not changed): the config; decompressing the
  chunks (the floor's own work); decoding the messages; the windows (splines, low-pass, clock
  measurements, moments: ``core.moments.reduce_block``); the solve of every sensor with its
  checks, timeline and std (``pipeline._solved``); what is left of the pass over the log
  (screening, the schedule, buffers); the document made and written.

Each figure is the least of ``--repeat`` rounds; the floor is :func:`throughput.floor`'s.

Run: ``python benchmarks/cpu_split.py [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
LIBRARIES = (
    "numpy, scipy.linalg, scipy.special, scipy.spatial.transform, typer.main, rich.console, "
    "yaml, mcap.reader, zstandard"
)
OWN = "imucal_cli.cli.app, imucal_cli.api, imucal_cli.pipeline, imucal_cli.core.calibrate"

#: Run in a fresh process: the calibration with its steps timed, printed as JSON (the libraries
#: imported first: their imports are a row of their own).
STEPS = f"""
import json, sys, time
import {LIBRARIES}
from imucal_cli import api, pipeline
from imucal_cli.core import streaming
from imucal_cli.documents import write_document
from imucal_cli.io import mcap_log
from imucal_cli import reading

spent = {{}}

def timed(owner, name, step):
    function = getattr(owner, name)
    def wrapper(*args, **kwargs):
        start = time.process_time()
        try:
            return function(*args, **kwargs)
        finally:
            spent[step] = spent.get(step, 0.0) + time.process_time() - start
    setattr(owner, name, wrapper)

timed(mcap_log, "decompress", "decompress")
timed(reading, "decode_imu", "decode")
timed(streaming, "reduce_block", "windows")
timed(pipeline, "_solved", "solve")
log, config, out = sys.argv[1:4]
start = time.process_time()
loaded = api.load_config(config, log)
spent["config"] = time.process_time() - start
start = time.process_time()
run = api.calibrate(log, loaded)
spent["calibrate"] = time.process_time() - start
start = time.process_time()
write_document(out, run.document())
spent["document"] = time.process_time() - start
print(json.dumps(spent))
"""


#: Run in a fresh process: the libraries' imports, then imucal's own, CPU seconds as JSON.
IMPORTS = f"""
import json, time
start = time.process_time()
import {LIBRARIES}
libraries = time.process_time()
import {OWN}
print(json.dumps({{"libraries": libraries - start, "own": time.process_time() - libraries}}))
"""


def python(code: str, *args: str) -> str:
    """What ``python -c code args`` prints, run in a fresh process."""
    return subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, check=True
    ).stdout


def fresh_cpu(code: str) -> float:
    """User + system CPU seconds of ``python -c code`` in a fresh process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-c", code], check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    sys.path.insert(0, str(HERE))
    from throughput import build, compile_package, floor

    log, config = build("1h", "mcap")
    compile_package()
    out = HERE / ".cache" / "cpu_split.yaml"
    best: dict[str, float] = {}
    for _ in range(args.repeat):
        found = {"floor": floor(log, "mcap")[1], "start": fresh_cpu("pass")}
        found.update(json.loads(python(IMPORTS)))
        found.update(json.loads(python(STEPS, str(log), str(config), str(out))))
        for key, value in found.items():
            best[key] = min(best.get(key, value), value)
    base = best["floor"]
    read_rest = best["calibrate"] - sum(
        best[k] for k in ("decompress", "decode", "windows", "solve")
    )
    rows = [
        ("the interpreter's start", best["start"]),
        ("the libraries' imports", best["libraries"]),
        ("imucal's own modules", best["own"]),
        ("the config", best["config"]),
        ("decompressing the chunks (the floor's work)", best["decompress"]),
        ("decoding the messages", best["decode"]),
        ("the rest of the pass: screening, the schedule, buffers", read_rest),
        ("the windows: splines, low-pass, clock, moments", best["windows"]),
        ("the solve: fits, checks, timeline, std", best["solve"]),
        ("the document made and written", best["document"]),
    ]
    print(f"floor (this run's): {base:.2f} CPU-s\n")
    print("| step | CPU s | / floor |")
    print("|---|---|---|")
    for what, cpu in rows:
        print(f"| {what} | {cpu:.2f} | {cpu / base:.2f} |")
    total = sum(cpu for _, cpu in rows)
    print(f"| **all** | {total:.2f} | {total / base:.2f} |")


if __name__ == "__main__":
    main()
