"""Shared fixtures. Compute tests need no viewer; Qt tests use napari's ``make_napari_viewer``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """The real scans in ../shared/data; tests using them skip cleanly where the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real scans not available ({SHARED_DATA} is absent)")
    return SHARED_DATA


def no_leftovers(folder: Path) -> list[Path]:
    """Temporary outputs of atomic writes left in ``folder`` (there must be none after an error)."""
    return [p for p in folder.rglob("*") if "unwind-tmp" in p.name]


#: The installed ``unwind`` command next to the interpreter running the tests.
UNWIND = Path(sys.executable).with_name("unwind")


def run_unwind(*args) -> tuple[int, str, str]:
    """Run ``unwind ARGS...`` as a user would; returns (exit status, stdout, stderr)."""
    r = subprocess.run([str(UNWIND), *map(str, args)], capture_output=True, text=True)
    return r.returncode, r.stdout, r.stderr
