"""The installed package's version, looked up when first asked (``importlib.metadata`` takes
50 ms to import)."""

from __future__ import annotations

from functools import cache


@cache
def version() -> str:
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("imucal")
    except PackageNotFoundError:  # running from a source tree that is not installed
        return "0.1.0"
