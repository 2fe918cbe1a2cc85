"""Faults: what imucal does with damaged logs, odd data and bad configs; prints markdown.

1. A matrix, fault x format -> outcome: exit code, the first line on stderr, messages recovered
   (of those written), whether a traceback or a partial output file was seen. Every fault is
   built from one simulated drive (aggressive, 60 s, two lidars) written in every format.
2. A fuzzer (seeded): random byte flips, truncations and field mutations (u32/u64 fields set to
   0, all ones or random) of real logs (the fixtures written by other tools in ``tests/data``
   and the simulated logs), each run through ``imucal inspect`` and ``imucal calibrate -o``,
   and every tenth also through ``imucal segments -o`` and ``imucal biases -o``.
   A case fails if it raised anything but a clean exit, printed a traceback, exited 2 with
   more than one line or without naming the file, or left an output file behind on failure.

0. The probes of hostile input (:mod:`hostile`): bombs, output paths, names, interrupts, each
   run as a process of its own and held to exit 0 or 2, no user file changed, 1 GB and a time
   bound; ``--probes`` runs these alone.

Run: ``python benchmarks/faults.py [--probes] [--cases 1000] [--seed 1]``. Everything runs
in-process through Typer's CliRunner (a traceback shows as an exception that is not SystemExit).
"""

from __future__ import annotations

import argparse
import shutil
import struct
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
from typer.testing import CliRunner

from imucal_cli.cli import app
from imucal_cli.documents import write_document
from imucal_cli.reading import read_imu
from imucal_cli.sim import DriveOptions, simulate_drive
from imucal_cli.sim.writers import FORMATS, TopicData, write_imu_log
from imucal_cli.types import ImuStream

ROOT = Path(__file__).resolve().parent.parent
NAMES = {
    "mcap": "d.mcap",
    "mcap-ros1": "d.mcap",
    "rosbag2-sqlite3": "d",
    "rosbag2-mcap": "d",
    "rosbag1": "d.bag",
}
runner = CliRunner()


def storage(log: Path) -> Path:
    if log.is_dir():
        return next(p for p in sorted(log.iterdir()) if p.suffix in (".db3", ".mcap"))
    return log


def copy(log: Path, target: Path) -> Path:
    if log.is_dir():
        shutil.copytree(log, target)
    else:
        target = target.with_suffix(log.suffix)
        shutil.copy(log, target)
    return target


def cut(fraction: float):
    def apply(log: Path) -> None:
        f = storage(log)
        data = f.read_bytes()
        f.write_bytes(data[: int(len(data) * fraction)])

    return apply


def corrupt_middle(log: Path) -> None:
    f = storage(log)
    data = bytearray(f.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 64] = bytes(64)
    f.write_bytes(bytes(data))


def no_index(log: Path) -> bool:
    """What a recorder killed before closing leaves: no summary (MCAP), no index (ROS 1), no
    metadata.yaml (rosbag2)."""
    if log.is_dir():
        (log / "metadata.yaml").unlink()
        return True
    data = bytearray(log.read_bytes())
    if log.suffix == ".bag":
        at = data.index(b"index_pos=") + len(b"index_pos=")
        index_pos = struct.unpack_from("<Q", data, at)[0]
        data[at : at + 8] = struct.pack("<Q", 0)
        log.write_bytes(bytes(data[:index_pos]))
        return True
    end = data.rfind(b"\x0f")  # the DataEnd record: everything after it is the summary
    while end > 0 and struct.unpack_from("<Q", data, end + 1)[0] != 4:
        end = data.rfind(b"\x0f", 0, end)
    log.write_bytes(bytes(data[:end]))
    return True


def broken_metadata(log: Path) -> bool:
    if not log.is_dir():
        return False
    (log / "metadata.yaml").write_text("rosbag2_bagfile_information: {version: [")
    return True


def edit_topic(drive, name: str, change) -> dict[str, TopicData]:
    topics = drive.topics()
    data = topics[name]
    t, g, a, log_ns = change(
        data.stream.t_ns.copy(),
        data.stream.gyro.copy(),
        data.stream.accel.copy(),
        data.log_time_ns.copy(),
    )
    order_free = ImuStream.__new__(ImuStream)  # out-of-order stamps are the point of some faults
    object.__setattr__(order_free, "t_ns", t)
    object.__setattr__(order_free, "gyro", g)
    object.__setattr__(order_free, "accel", a)
    object.__setattr__(order_free, "frame_id", data.stream.frame_id)
    topics[name] = TopicData(order_free, log_ns)
    return topics


def nan_samples(t, g, a, log_ns):
    rng = np.random.default_rng(0)
    rows = rng.choice(len(t), size=len(t) // 100, replace=False)
    g[rows[: len(rows) // 2], 0] = np.nan
    a[rows[len(rows) // 2 :], 2] = np.inf
    return t, g, a, log_ns


def saturated(t, g, a, log_ns):
    """Five pothole hits that drive a +-2 g accelerometer to its end stop for 4 samples each."""
    for k, at in enumerate(np.linspace(0.2, 0.8, 5) * len(t)):
        a[int(at) : int(at) + 4, 2] = (1 if k % 2 else -1) * 2 * 9.80665
    return t, g, a, log_ns


def duplicates_and_disorder(t, g, a, log_ns):
    rng = np.random.default_rng(1)
    for i in rng.choice(len(t) - 2, size=50, replace=False):
        t[i], t[i + 1] = t[i + 1], t[i]
    dup = rng.choice(len(t) - 1, size=50, replace=False)
    t[dup + 1] = t[dup]
    return t, g, a, log_ns


def zero_stamps(t, g, a, log_ns):
    t[::7] = 0
    return t, g, a, log_ns


def gap(t, g, a, log_ns):
    keep = (t < t[0] + 20 * 10**9) | (t > t[0] + 30 * 10**9)
    return t[keep], g[keep], a[keep], log_ns[keep]


def clock_jump(t, g, a, log_ns):
    t[len(t) // 2 :] += 300 * 10**9
    return t, g, a, log_ns


def power_on_clock(t, g, a, log_ns):
    return t - t[0] + 12_345_000_000, g, a, log_ns


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--only",
        type=lambda v: {int(x) for x in v.split(",")},
        default=None,
        help="replay these fuzz cases",
    )
    parser.add_argument(
        "--probes",
        action="store_true",
        help="only the probes of hostile input (benchmarks/hostile.py)",
    )
    parser.add_argument("--probe", default="", help="only the probes whose name holds this")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="imucal-faults-"))
    try:
        if args.only is None:
            from hostile import probes

            probes(work / "probes", args.probe)
        if args.only is None and not args.probes:
            matrix(work)
        if not args.probes:
            fuzz(work, args.cases, args.seed, args.only)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def run(argv: list[str], out: Path | None) -> dict:
    if out is not None and out.exists():
        out.unlink()
    result = runner.invoke(app, argv)
    traceback = result.exception is not None and not isinstance(result.exception, SystemExit)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("imucal: error")]
    partial = out is not None and result.exit_code != 0 and out.exists()
    trace = ""
    if traceback and result.exc_info is not None:
        import traceback as tb

        trace = "".join(tb.format_exception(*result.exc_info)[-3:])
    return {
        "trace": trace,
        "code": result.exit_code,
        "traceback": traceback or "Traceback" in result.output,
        "partial": partial,
        "error": errors[0] if errors else "",
        "lines": lines,
        "stderr": result.stderr,
    }


def matrix(work: Path) -> None:
    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=60.0, seed=7))
    short = simulate_drive(DriveOptions(scenario="aggressive", duration_s=3.0, seed=7))
    still = simulate_drive(DriveOptions(scenario="stationary", duration_s=60.0, seed=7))
    config = work / "config.yaml"
    write_document(config, drive.config_document())
    base_topics = list(drive.topics())
    sensor = base_topics[1]

    unknown_key = work / "unknown.yaml"
    document = drive.config_document()
    document["calibration"] = dict(document.get("calibration", {}), max_time_ofset_s=0.1)
    write_document(unknown_key, document)
    missing_topic = work / "missing.yaml"
    document = drive.config_document()
    first = next(iter(document["sensors"]))
    document["sensors"][first]["imu_topic"] = "/lidar/nope/imu"
    write_document(missing_topic, document)

    faults: list[tuple[str, object]] = [
        ("cut at 50%", cut(0.5)),
        ("cut at 90%", cut(0.9)),
        ("64 bytes zeroed mid-file", corrupt_middle),
        ("no summary / index / metadata.yaml", no_index),
        ("broken metadata.yaml", broken_metadata),
        ("1% NaN/Inf samples", ("topics", nan_samples)),
        ("accel clipped at +-2 g (5 hits x 4 samples)", ("topics", saturated)),
        ("duplicate + out-of-order stamps", ("topics", duplicates_and_disorder)),
        ("zero stamps (1 in 7)", ("topics", zero_stamps)),
        ("10 s gap on a lidar IMU", ("topics", gap)),
        ("clock jump +5 min", ("topics", clock_jump)),
        ("lidar IMU on power-on clock", ("topics", power_on_clock)),
        ("3 s log (too short)", ("drive", short)),
        ("motionless 60 s", ("drive", still)),
        ("missing topic", ("config", missing_topic)),
        ("unknown config key", ("config", unknown_key)),
        ("output folder missing", ("out", None)),
    ]
    rows = []
    tracebacks = partials = 0
    start = time.perf_counter()
    for fmt in FORMATS:
        folder = work / fmt
        folder.mkdir()
        clean = write_imu_log(folder / NAMES[fmt], fmt, drive.topics())
        written = {t: len(read_imu(clean, base_topics)[t].stream) for t in base_topics}
        for number, (name, fault) in enumerate(faults):
            target = folder / f"f{number}"
            cfg = config
            out = folder / f"out{number}.yaml"
            if callable(fault):
                log = copy(clean, target)
                if fault(log) is False:
                    shutil.rmtree(log, ignore_errors=True) if log.is_dir() else log.unlink()
                    continue
            else:
                kind, value = fault
                if kind == "topics":
                    topic = base_topics[0] if value is clock_jump else sensor
                    log = write_imu_log(
                        target.with_suffix(clean.suffix) if clean.suffix else target,
                        fmt,
                        edit_topic(drive, topic, value),
                    )
                elif kind == "drive":
                    log = write_imu_log(
                        target.with_suffix(clean.suffix) if clean.suffix else target,
                        fmt,
                        value.topics(),
                    )
                elif kind == "config":
                    log, cfg = clean, value
                else:
                    log, out = clean, folder / "no" / "such" / "out.yaml"
            result = run(["calibrate", str(log), "-c", str(cfg), "-o", str(out)], out)
            tracebacks += result["traceback"]
            partials += result["partial"]
            try:
                read = read_imu(log, base_topics)
                recovered = sum(len(r.stream) for r in read.values())
            except Exception:
                recovered = 0
            message = result["error"] or next(
                (
                    line
                    for key in ("not read", "warning", "note")
                    for line in result["lines"]
                    if key in line
                ),
                "",
            )
            message = message.replace(str(work) + "/", "")
            if result["code"] == 0 and out.exists():
                import yaml

                statuses = sorted(
                    {s["status"] for s in yaml.safe_load(out.read_text())["sensors"].values()}
                )
                message = f"status {'/'.join(statuses)}" + (f"; {message}" if message else "")
            rows.append(
                (
                    name,
                    fmt,
                    result["code"],
                    recovered,
                    sum(written.values()),
                    message[:150],
                    result["traceback"],
                    result["partial"],
                )
            )
    print(
        f"## Fault matrix ({len(rows)} runs of `imucal calibrate -o`, "
        f"{time.perf_counter() - start:.0f} s)\n"
    )
    print(
        "| fault | format | exit | messages recovered / written | first error, warning or note on "
        "stderr | traceback | partial output |"
    )
    print("|---|---|---|---|---|---|---|")
    for name, fmt, code, recovered, total, message, tb, partial in rows:
        print(
            f"| {name} | {fmt} | {code} | {recovered:,} / {total:,} | {message.replace('|', '/')} "
            f"| {'YES' if tb else 'no'} | {'YES' if partial else 'no'} |"
        )
    print(f"\nTracebacks: {tracebacks}. Partial output files: {partials}.\n")
    sys.stdout.flush()


def mutate(data: bytes, rng: np.random.Generator) -> tuple[bytes, str]:
    kind = rng.choice(["flip", "truncate", "field", "flip+truncate"])
    out = bytearray(data)
    n = len(out)
    if kind in ("flip", "flip+truncate"):
        count = int(rng.integers(1, 33))
        for pos in rng.integers(0, n, size=count):
            out[pos] ^= 1 << int(rng.integers(0, 8))
    if kind == "field":
        for _ in range(int(rng.integers(1, 5))):
            width = int(rng.choice([4, 8]))
            pos = int(rng.integers(0, max(1, n - width)))
            value = [0, (1 << (8 * width)) - 1, int(rng.integers(0, 1 << 31))][
                int(rng.integers(0, 3))
            ]
            out[pos : pos + width] = value.to_bytes(width, "little")
    if kind in ("truncate", "flip+truncate"):
        out = out[: int(rng.integers(0, n))]
    return bytes(out), str(kind)


def fuzz(work: Path, cases: int, seed: int, only: set[int] | None = None) -> None:
    rng = np.random.default_rng(seed)
    drive = simulate_drive(DriveOptions(scenario="aggressive", duration_s=25.0, seed=3))
    config = work / "fuzz.yaml"
    write_document(config, drive.config_document())
    fixture_config = work / "fixture.yaml"
    document = drive.config_document()
    document["base"]["topic"] = "/imu/data"
    first = next(iter(document["sensors"]))
    document["sensors"] = {
        first: dict(document["sensors"][first], imu_topic="/chatter")
    }  # wrong type: exit 2 naming both
    write_document(fixture_config, document)
    seeds: list[tuple[Path, Path]] = []
    for fmt in FORMATS:
        (work / "fz" / fmt).mkdir(parents=True)
        seeds.append((write_imu_log(work / "fz" / fmt / NAMES[fmt], fmt, drive.topics()), config))
    data = ROOT / "tests" / "data"
    for name in (
        "ros1_rosbag.bag",
        "ros1_mcap_ros1_writer.mcap",
        "ros2_mcap_ros2_writer.mcap",
        "rosbag2_converted_sqlite3",
    ):
        seeds.append((data / name, fixture_config))
    outcomes: Counter[str] = Counter()
    failures: list[str] = []
    start = time.perf_counter()
    for case in range(cases):
        source, cfg = seeds[case % len(seeds)]
        if only is not None and case not in only:
            mutate(storage(source).read_bytes(), rng)  # the same random sequence as a full run
            continue
        target = work / "case" / f"{case}"
        target.parent.mkdir(exist_ok=True)
        log = copy(source, target)
        f = storage(log)
        mutated, kind = mutate(f.read_bytes(), rng)
        f.write_bytes(mutated)
        out = work / "case" / f"{case}.yaml"
        commands = [["inspect", str(log)], ["calibrate", str(log), "-c", str(cfg), "-o", str(out)]]
        if case % 10 == 0:  # the other commands that read logs, on every tenth case
            commands += [
                ["segments", str(log), "-c", str(cfg), "-o", str(out)],
                ["biases", str(log), "-c", str(cfg), "-o", str(out)],
            ]
        for command in commands:
            result = run(command, out if command[0] != "inspect" else None)
            outcomes[f"{command[0]} exit {result['code']}"] += 1
            problem = ""
            if result["traceback"]:
                problem = "traceback"
            elif result["partial"]:
                problem = "partial output"
            elif result["code"] == 2 and (
                len(result["lines"]) != 1 or str(log) not in result["error"]
            ):
                problem = "exit 2 without one line naming the file"
            elif result["code"] not in (0, 1, 2):
                problem = f"exit {result['code']}"
            if problem:
                failures.append(
                    f"case {case} ({source.name}, {kind}, {command[0]}): {problem}: "
                    f"{(result['trace'] or result['stderr'])[-400:]!r}"
                )
        shutil.rmtree(log, ignore_errors=True) if log.is_dir() else log.unlink()
        if out.exists():
            out.unlink()
    print(
        f"## Fuzzer ({cases} mutated logs, seed {seed}, {sum(outcomes.values())} runs, "
        f"{time.perf_counter() - start:.0f} s)\n"
    )
    print("| outcome | runs |")
    print("|---|---|")
    for key, count in sorted(outcomes.items()):
        print(f"| {key} | {count} |")
    print(f"\nFailures (traceback, partial output, unclear exit 2): {len(failures)}")
    for line in failures[:20]:
        print(f"- {line}")


if __name__ == "__main__":
    main()
