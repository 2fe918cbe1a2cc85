"""What imucal says of the real two-IMU rigs (``../shared/realdata/multi_imu``); prints tables.

For each rig: the whole run calibrated as a user would (``imucal_cli.calibrate``, the rig's
config with both IMUs declared consumer MEMS parts, SPEC "IMU grades"), against its truth; then
the run
split in time into parts of equal length, each calibrated alone, and every two parts compared:
the difference of their estimates (rotation about the base axes, translation) against the
combined statistical std (``sqrt(var_a + var_b)`` per axis: what more driving shrinks, so what
two drives of one rig differ by).

Run: ``python benchmarks/real_rigs.py [--parts 3]``.
"""

from __future__ import annotations

import argparse
from itertools import combinations, pairwise
from pathlib import Path

import numpy as np

from imucal_cli.api import DriveStreams, calibrate, calibrate_streams, load_transforms
from imucal_cli.config import Config, parse_config
from imucal_cli.documents import load_document
from imucal_cli.errors import ImucalError
from imucal_cli.reading import ImuBatches
from imucal_cli.types import ImuStream

RIGS = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "multi_imu"


def rig_config(folder: Path) -> Config:
    """The rig's config with both IMUs declared what they are: consumer MEMS parts."""
    document = load_document(folder / "config.yaml")
    document["base"]["grade"] = "consumer"
    for sensor in document["sensors"].values():
        sensor["grade"] = "consumer"
    return parse_config(document, str(folder / "config.yaml"))


def truth_notes(folder: Path) -> str:
    """The truth file's notes: how good it is (a placeholder translation is not scored)."""
    return str(load_document(folder / "truth.yaml").get("notes", ""))


def read_streams(log: Path, config: Config) -> DriveStreams:
    """Every message of the base and sensor topics, in memory (the rigs are small)."""
    topics = {config.base.topic: "base"} | {s.imu_topic: s.name for s in config.sensors}
    parts: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {
        n: [] for n in topics.values()
    }
    for topic, _, t, w, f in ImuBatches(log, list(topics)):
        parts[topics[topic]].append((t, w, f))
    streams = {
        name: ImuStream(*(np.concatenate([p[i] for p in chunks]) for i in range(3)))
        for name, chunks in parts.items()
    }
    base = streams.pop("base")
    return DriveStreams(base, streams, int(base.t_ns[0]))


def _slice(stream: ImuStream, start: int, end: int) -> ImuStream:
    keep = (stream.t_ns >= start) & (stream.t_ns < end)
    return ImuStream(stream.t_ns[keep], stream.gyro[keep], stream.accel[keep])


def split(streams: DriveStreams, parts: int) -> list[DriveStreams]:
    """The run cut in time into ``parts`` of equal length (over the span every IMU covers)."""
    start = max([int(s.t_ns[0]) for s in streams.sensors.values()] + [int(streams.base.t_ns[0])])
    end = min([int(s.t_ns[-1]) for s in streams.sensors.values()] + [int(streams.base.t_ns[-1])])
    edges = np.linspace(start, end + 1, parts + 1).astype(np.int64)
    return [
        DriveStreams(
            _slice(streams.base, a, b),
            {n: _slice(s, a, b) for n, s in streams.sensors.items()},
            int(a),
        )
        for a, b in pairwise(edges)
    ]


def agreement(result_a, result_b, name: str) -> np.ndarray | None:
    """Per axis (rotation about base axes, translation) the two parts' difference over their
    combined statistical std, or None where either part could not place the sensor."""
    a, b = result_a.estimates[name], result_b.estimates[name]
    if a.statistical_covariance is None or b.statistical_covariance is None:
        return None
    Ta, Tb = a.T_base_imu, b.T_base_imu
    delta = np.concatenate(
        [(Ta.rotation * Tb.rotation.inv()).as_rotvec(), Ta.translation - Tb.translation]
    )
    combined = np.diag(a.statistical_covariance) + np.diag(b.statistical_covariance)
    observable = a.translation_observable & b.translation_observable
    keep = np.concatenate([np.ones(3, dtype=bool), observable])
    return (delta / np.sqrt(combined))[keep]


def header(*columns: str) -> None:
    """A markdown table's header and its separator, one cell per column."""
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parts", type=int, default=3)
    args = parser.parse_args()
    rigs = sorted(p for p in RIGS.iterdir() if (p / "log.mcap").exists()) if RIGS.exists() else []
    if not rigs:
        raise SystemExit(f"no rig recordings under {RIGS}")
    print("## The whole run against the truth (both IMUs declared consumer)\n")
    header(
        "rig",
        "status",
        "dR deg (x, y, z)",
        "total rotation std deg",
        "dt mm",
        "total translation std mm",
        "statistical rotation std deg",
        "scored",
        "largest error / total std (scored axes)",
    )
    wrong_ok = 0
    for folder in rigs:
        config = rig_config(folder)
        run = calibrate(folder / "log.mcap", config)
        truth = load_transforms(folder / "truth.yaml")["imu2"]
        sensor = run.document()["sensors"]["imu2"]
        T = run.T_base_lidar("imu2")
        d_rot = np.degrees((truth.rotation * T.rotation.inv()).as_rotvec())
        dt = 1e3 * (T.translation - truth.translation)
        estimate = run.estimates["imu2"]
        stat = (
            np.degrees(np.sqrt(np.diag(estimate.statistical_covariance)[:3]))
            if estimate.statistical_covariance is not None
            else None
        )

        def fmt(v, digits):
            return "-" if v is None else ", ".join(f"{x:.{digits}f}" for x in v)

        std_r = sensor.get("rotation_std_deg")
        std_t = sensor.get("translation_std_m")
        # a truth whose translation is a placeholder (its notes say so) scores the rotation only
        scored = "rotation" if "placeholder" in str(truth_notes(folder)).lower() else "both"
        ratio = None
        if std_r is not None and std_t is not None:
            ratios = np.abs(d_rot) / np.array(std_r)
            if scored == "both":
                ratios = np.concatenate([ratios, np.abs(dt) / (1e3 * np.array(std_t))])
            ratio = float(ratios.max())
            wrong_ok += sensor["status"] == "ok" and ratio > 4
        print(
            f"| {folder.name} | {sensor['status']} | {fmt(d_rot, 2)} | {fmt(std_r, 2)} | "
            f"{fmt(dt, 1)} | {fmt(None if std_t is None else 1e3 * np.array(std_t), 1)} | "
            f"{fmt(stat, 3)} | {scored} | {'-' if ratio is None else f'{ratio:.2f}'} |"
        )
    print(f"\n**`ok` beyond 4 total std on a scored axis: {wrong_ok} (must be 0).**")
    print(f"\n## Parts of each run against each other ({args.parts} parts of equal length)\n")
    header(
        "rig",
        "part statuses",
        "pairs compared",
        "axes within 3 combined statistical std",
        "largest",
    )
    for folder in rigs:
        config = rig_config(folder)
        streams = read_streams(folder / "log.mcap", config)
        results, statuses = [], []
        for part in split(streams, args.parts):
            try:
                results.append(calibrate_streams(part, config))
                statuses.append(results[-1].estimates["imu2"].status)
            except ImucalError as exc:  # a part inside a gap of the recording
                statuses.append(f"not calibrated ({str(exc).split(':')[0]})")
        ratios = [agreement(a, b, "imu2") for a, b in combinations(results, 2)]
        kept = [r for r in ratios if r is not None]
        if not kept:
            print(f"| {folder.name} | {', '.join(statuses)} | 0 | - | - |")
            continue
        every = np.abs(np.concatenate(kept))
        print(
            f"| {folder.name} | {', '.join(statuses)} | {len(kept)} | "
            f"{(every <= 3).mean():.0%} of {every.size} | {every.max():.1f} |"
        )


if __name__ == "__main__":
    main()
