"""Output paths that never cost a user a file.

The rule every command follows: imucal never deletes or overwrites a file it did not create in
this run, except an output the user named explicitly that is none of the run's inputs. So an
output is checked, before any work, against every input (a rosbag2 log is its whole folder,
also when it is given as its ``metadata.yaml``), and a log is only ever replaced (``simulate
--force``) when it is recognisably a log.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path

from imucal_cli.errors import InputError
from imucal_cli.io.formats import ROSBAG2_FILES, by_magic


def log_folder(path: Path) -> Path:
    """The log a path stands for: a rosbag2 folder for its ``metadata.yaml`` or for one of its
    storage files; the path itself otherwise."""
    if path.name == "metadata.yaml" or (
        path.suffix in ROSBAG2_FILES and (path.parent / "metadata.yaml").is_file()
    ):
        return path.parent
    return path


def _resolved(path: Path) -> Path:
    return Path(os.path.realpath(path))


def check_outputs(outputs: Mapping[str, Path | None], inputs: Iterable[Path | None]) -> None:
    """Refuse, before any work, an output that is one of the inputs, lies inside an input's
    folder (a rosbag2 log), is an existing folder, or is named twice. ``outputs`` maps how
    each was given (``-o``, ``--junit``) to its path."""
    roots: dict[Path, Path] = {}
    for given in inputs:
        if given is None:
            continue
        for path in {given, log_folder(given)}:
            roots.setdefault(_resolved(path), given)
    seen: dict[Path, str] = {}
    for option, out in outputs.items():
        if out is None:
            continue
        real = _resolved(out)
        if real.is_dir():
            raise InputError(f"{out}: {option} is a folder: give a file name")
        if real in seen:
            raise InputError(f"{out}: {option} and {seen[real]} name the same file")
        seen[real] = option
        if real.is_file() and recognised_log(real):
            raise InputError(f"{out}: {option} is a log: a log is never an output")
        if (real.parent / "metadata.yaml").is_file():
            raise InputError(
                f"{out}: {option} lies inside the rosbag2 log {out.parent}: give another output"
            )
        for root, given in roots.items():
            if real == root:
                raise InputError(
                    f"{out}: {option} is {given}, an input of this run: give another output"
                )
            if root.is_dir() and root in real.parents:
                raise InputError(
                    f"{out}: {option} lies inside {given}, an input of this run: give another "
                    "output"
                )


def recognised_log(path: Path) -> bool:
    """Whether ``path`` is something imucal could have written as a log: an MCAP or ROS 1 bag
    file by its magic bytes, or a rosbag2 folder holding only its metadata and storage files."""
    if path.is_symlink():
        return False
    if path.is_file():
        with path.open("rb") as handle:
            return by_magic(handle.read(16)) is not None
    if path.is_dir():
        entries = list(path.iterdir())
        return (path / "metadata.yaml").is_file() and all(
            entry.is_file()
            and not entry.is_symlink()
            and (entry.name == "metadata.yaml" or entry.name.endswith(ROSBAG2_FILES))
            for entry in entries
        )
    return False


def refuse_existing(path: Path, force: bool, what: str = "a log") -> None:
    """An existing ``path`` is kept unless ``force``, and then replaced only if it is ``what``
    imucal recognises (:func:`recognised_log`); the current folder and those above it never."""
    if not (path.exists() or path.is_symlink()):
        return
    real, here = _resolved(path), Path.cwd().resolve()
    if real == here or real in here.parents:
        raise InputError(f"{path}: is the current folder or one above it: name a new log")
    if not force:
        raise InputError(
            f"{path}: exists: name a new one, or give --force to replace it ({what} only)"
        )
    if not recognised_log(path):
        raise InputError(f"{path}: exists and is not a log imucal recognises: not replaced")


@contextmanager
def only_writer(folder: Path) -> Iterator[None]:
    """Hold ``folder`` (made if missing) for this process alone while the block runs: a second
    run into it at once is refused (an exclusive ``flock`` of the folder itself, let go when
    the process ends however it ends), never left to replace the first's results."""
    made = not folder.exists()
    try:
        folder.mkdir(exist_ok=True)
        handle = os.open(folder, os.O_RDONLY)
    except OSError as exc:
        raise InputError(f"{folder}: cannot make or open the folder: {exc.strerror}") from None
    try:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise InputError(
                f"{folder}: another imucal run is writing into it: wait for it, or give another "
                "folder"
            ) from None
        try:
            yield
        except BaseException:
            if made and not any(folder.iterdir()):
                folder.rmdir()  # (nothing written: leave no folder either)
            raise
    finally:
        os.close(handle)
