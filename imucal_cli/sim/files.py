"""A simulated drive written as ``imucal simulate`` writes it: the log, with its truth and its
config beside it (``STEM.truth.yaml``, ``STEM.config.yaml``)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from imucal_cli.errors import InputError
from imucal_cli.sim.drive import BiasTrack, DriveOptions, drive_pieces, with_errors
from imucal_cli.sim.writers import write_imu_log


@dataclass(frozen=True)
class Written:
    log: Path
    truth: Path
    config: Path
    #: Messages written per topic.
    counts: dict[str, int]


def beside(out: Path, force: bool) -> tuple[Path, Path]:
    """The truth and config files beside OUT, checked before any work: an existing log OUT is
    replaced only with ``force`` and only if it is a log; its truth and config likewise, and
    only if they are such documents."""
    from imucal_cli.documents import load_document
    from imucal_cli.paths import refuse_existing

    refuse_existing(out, force)
    stem = out.with_suffix("") if out.suffix.lower() in {".mcap", ".bag"} else out
    truth, config = (stem.with_name(stem.name + end) for end in (".truth.yaml", ".config.yaml"))
    for path in (truth, config):
        if not (path.exists() or path.is_symlink()):
            continue
        if not force:
            raise InputError(f"{path}: exists: name a new log, or give --force to replace it")
        try:
            document = load_document(path) if path.is_file() and not path.is_symlink() else None
        except InputError:
            document = None
        if not isinstance(document, dict) or "sensors" not in document:
            raise InputError(
                f"{path}: exists and is not a truth or config imucal wrote: not replaced"
            )
    return truth, config


def simulate_files(
    out: Path,
    fmt: str,
    options: DriveOptions,
    errors: str = "none",
    grades: tuple[str | None, str | None] = (None, None),
    tf_static: bool = False,
    force: bool = False,
    progress: Callable[[int, int | None], None] | None = None,
) -> Written:
    """Simulate a drive with the error class ``errors`` and the (lidar, base) ``grades`` and
    write it piece by piece (memory does not grow with its length)."""
    from imucal_cli.core.grades import GRADES
    from imucal_cli.documents import write_document

    truth_path, config_path = beside(out, force)
    for key, grade in zip(("--lidar-grade", "--base-grade"), grades, strict=True):
        if grade is not None and grade not in GRADES:
            raise InputError(f"{key}: {grade!r} is not one of {', '.join(GRADES)}")
    try:
        options = with_errors(options, errors)
        options = replace(
            options,
            lidar_grade=grades[0] or options.lidar_grade,
            base_grade=grades[1] or options.base_grade,
            tf_static=tf_static,
        )
        pieces = drive_pieces(options)
        drive = next(pieces)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    track = BiasTrack(drive)
    counts = {topic: len(data.stream) for topic, data in drive.topics().items()}

    def later() -> Iterator[Any]:
        for piece in pieces:
            track.add(piece)
            for topic, data in piece.topics().items():
                counts[topic] += len(data.stream)
            yield piece.topics()

    write_imu_log(
        out, fmt, drive.topics(), progress, force, drive.static_transforms(), later=(later(), None)
    )
    write_document(truth_path, drive.truth_document(track))
    write_document(config_path, drive.config_document())
    return Written(out, truth_path, config_path, counts)
