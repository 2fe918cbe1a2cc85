"""The package's size at several commits, counted alike; prints markdown tables (docs/design.md).

A raw line count moves with formatting: holding lines to 100 characters (``ruff format``) added
about 1,700 lines to the package at once without changing a statement. So each commit's
``imucal_cli/`` is taken out of git into a scratch folder, formatted there with this checkout's
settings (line length 100, Python 3.11), and counted four ways:

- lines as committed, and lines once formatted alike;
- statements (every ``ast.stmt``) and tokens (names, operators, literals; not comments, not
  docstrings): two counts that no formatting moves;
- the longest function in ``core/`` (lines, formatted) and the estimator's lines: the
  measurement model, solver, checks, uncertainty and status policy, wherever they live
  (``core/calibrate.py`` alone at first, then it and its successors).

With ``--growth``, a second table: what each issue's commits since ``fa40f20`` added to and
removed from ``imucal_cli/`` as committed (``git log --numstat``). Issue 29's rebuild ran
alongside issues 28, 30, 31 and 32, so every such commit is put with the issue its stop's closing
note names it under (:data:`ISSUE_OF`); the commit that formatted the package is a row of its own.

Run: ``python benchmarks/sizes.py [REV ...] [--growth]`` (default: ``fa40f20 HEAD``, the commit
issue 29 was filed at and now), from a git checkout.
"""

from __future__ import annotations

import argparse
import ast
import io
import subprocess
import sys
import tarfile
import tempfile
import tokenize
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
RUFF = [
    sys.executable,
    "-m",
    "ruff",
    "format",
    "--isolated",
    "--line-length",
    "100",
    "--target-version",
    "py311",
    "-q",
]
ESTIMATOR = (
    "calibrate.py",
    "model.py",
    "solver.py",
    "checks.py",
    "status.py",
    "uncertainty.py",
    "moments.py",
)


#: The commits since ``fa40f20`` that changed ``imucal_cli/`` for an issue other than 29 (short
#: hashes), and issue 29's that formatted it and that made it fast; every other one is issue
#: 29's rebuild.
ISSUE_OF = {
    "28, 32": "6f54b84 d6ba144 a96f1c8 acbd979 9973d76 e36fa9b 3905ed0 3f3ee01 b7bb953 f375ca0 "
    "68fd997 2aa6bd7 5eab0b3 a378c81 46a9577 d2f2052 302e77b 83a745c e445237 e0ed2a4 c3d2a4b "
    "22161f1 5f386f0",
    "30": "74be268 61f019d 337c288 2678959 eadb491 78a0662 af698d9 66e1179 9074610 203b696 "
    "7d59e12 7fcb263 1ea9dad 01b17ce cf3303b ea4702a dd48795 47b536c",
    "31": "7f1480c c400b14 3b8f4a6 6f745d2 b2fe229 a999c11 09b4447 9286513 ac432a9 d70f585 abdbdd2",
    "29: ruff format, 100 characters, 60-line functions": "76d7717",
    "29: speed (the 4x bound)": "fbe8711 556b8c0 6218a1c 6da139b 4ab53f3 0f1c8e1 b4962e4 9d9d4a3 "
    "25174a9 d8ad0b6 7b2940a b40481f 067fe99 b4df93b 170fe69 3e03f70 d2c6200 4c46855 e2d5565 "
    "793eafc 3d17cd0 50d5397 9165146 75ea4a2 a3856a1 c8bc4f5 85d59aa c35827a 3b95fe1 2a7b530 "
    "1fa25ff 9f06584",
}


def growth(since: str) -> dict[str, list[int]]:
    """Per issue: commits, lines added and lines removed in ``imucal_cli/`` since ``since``."""
    group = {h: name for name, hashes in ISSUE_OF.items() for h in hashes.split()}
    command = ["git", "-C", str(REPO), "log", "--numstat", "--format=@%h", f"{since}..HEAD"]
    log = subprocess.run(
        [*command, "--", "imucal_cli"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    totals: dict[str, list[int]] = {}
    row: list[int] = []
    for line in log.splitlines():
        if line.startswith("@"):
            row = totals.setdefault(
                group.get(line[1:], "29: the model, one pipeline, the split"), [0, 0, 0]
            )
            row[0] += 1
        elif line.strip():
            added, removed, _ = line.split("\t")
            row[1] += int(added)
            row[2] += int(removed)
    return totals


def checkout(rev: str, into: Path) -> Path:
    """``imucal_cli/`` of ``rev``, extracted under ``into``."""
    archive = subprocess.run(
        ["git", "-C", str(REPO), "archive", rev, "imucal_cli"], capture_output=True, check=True
    ).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        if hasattr(tarfile, "data_filter"):  # Python 3.11.4 and later
            tar.extractall(into, filter="data")
        else:  # git's own archive of this repository: paths inside `into` by construction
            tar.extractall(into)
    return into / "imucal_cli"


def lines(root: Path) -> int:
    return sum(len(p.read_text().splitlines()) for p in root.rglob("*.py"))


def _docstrings(tree: ast.Module) -> set[int]:
    """First lines of the module's, classes' and functions' docstrings."""
    kinds = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
    return {
        node.body[0].lineno
        for node in ast.walk(tree)
        if isinstance(node, kinds)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
        and isinstance(node.body[0].value.value, str)
    }


SKIPPED = {
    tokenize.COMMENT,
    tokenize.NL,
    tokenize.NEWLINE,
    tokenize.INDENT,
    tokenize.DEDENT,
    tokenize.ENDMARKER,
}


def counts(root: Path) -> tuple[int, int]:
    """Statements and tokens (no comments, no docstrings) of every module under ``root``."""
    statements = tokens = 0
    for path in root.rglob("*.py"):
        text = path.read_text()
        tree = ast.parse(text)
        statements += sum(isinstance(node, ast.stmt) for node in ast.walk(tree))
        docs = _docstrings(tree)
        for token in tokenize.generate_tokens(io.StringIO(text).readline):
            if token.type in SKIPPED or (token.type == tokenize.STRING and token.start[0] in docs):
                continue
            tokens += 1
    return statements, tokens


def longest_function(root: Path) -> tuple[int, str]:
    """The longest function (lines) under ``root``, and its name."""
    found = (0, "")
    for path in root.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                size = node.end_lineno - node.lineno + 1  # type: ignore[operator]
                found = max(found, (size, f"{path.stem}.{node.name}"))
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("revs", nargs="*", default=["fa40f20", "HEAD"])
    parser.add_argument("--growth", action="store_true", help="lines added and removed by issue")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for rev in args.revs:
            package = checkout(rev, Path(scratch) / rev)
            committed = lines(package)
            subprocess.run([*RUFF, str(package)], check=True)
            statements, tokens = counts(package)
            size, name = longest_function(package / "core")
            estimator = sum(
                len((package / "core" / m).read_text().splitlines())
                for m in ESTIMATOR
                if (package / "core" / m).exists()
            )
            rows.append(
                (rev, committed, lines(package), statements, tokens, f"{size} ({name})", estimator)
            )
    print(
        "| commit | lines | lines, formatted alike | statements | tokens | "
        "longest core function, lines | estimator lines |"
    )
    print("|---|---|---|---|---|---|---|")
    for rev, committed, formatted, statements, tokens, longest, estimator in rows:
        print(
            f"| {rev} | {committed:,} | {formatted:,} | {statements:,} | {tokens:,} | {longest} "
            f"| {estimator:,} |"
        )
    if args.growth:
        print()
        print(f"| issue (commits since {args.revs[0]}) | commits | added | removed | net |")
        print("|---|---|---|---|---|")
        totals = growth(args.revs[0])
        for name in sorted(totals):
            commits, added, removed = totals[name]
            print(f"| {name} | {commits} | {added:,} | {removed:,} | {added - removed:+,} |")
        commits, added, removed = (sum(v[i] for v in totals.values()) for i in range(3))
        print(f"| all | {commits} | {added:,} | {removed:,} | {added - removed:+,} |")


if __name__ == "__main__":
    main()
