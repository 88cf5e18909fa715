"""The order plugin CI runs the suite with (scripts/pytest_order.py): ``--order-only DIR`` reorders the files under
DIR among the places they hold and leaves every other test where the default run puts it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _order(tmp_path, *args):
    env = dict(os.environ, PYTHONPATH=str(ROOT / "scripts"), PYTEST_DISABLE_PLUGIN_AUTOLOAD="1")
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--co", "-q", "-p", "no:cacheprovider", "-p", "pytest_order", *args,
         "-c", os.devnull, "--rootdir", str(tmp_path), str(tmp_path)],
        capture_output=True, text=True, env=env, cwd=tmp_path, check=True).stdout
    return [line for line in out.splitlines() if "::" in line]


def test_only_the_files_under_the_directory_are_shuffled_and_in_the_places_they_held(tmp_path):
    for d in ("a", "gui", "z"):
        (tmp_path / d).mkdir()
    for d, names in {"a": "pq", "gui": "bcdefgh", "z": "rs"}.items():
        for n in names:
            (tmp_path / d / f"test_{n}.py").write_text(
                "".join(f"def test_{n}{k}():\n    pass\n" for k in range(4)))
    default = _order(tmp_path)
    shuffled = _order(tmp_path, "--order-seed", "3", "--order-only", str(tmp_path / "gui"))
    assert sorted(shuffled) == sorted(default)
    # every test outside gui/ at the same index as in the default run
    assert [(i, t) for i, t in enumerate(shuffled) if "gui/" not in t] == \
        [(i, t) for i, t in enumerate(default) if "gui/" not in t]
    gui = [t for t in shuffled if "gui/" in t]
    files = [t.split("::")[0] for t in gui]
    assert files != sorted(files)  # the files moved
    assert gui != sorted(gui, key=lambda t: (files.index(t.split("::")[0]), t))  # and the tests inside them
    # each file's tests stay together (module fixtures built once)
    assert len({f for f in files}) == len([f for k, f in enumerate(files) if k == 0 or files[k - 1] != f])
    # without --order-only every file moves
    whole = _order(tmp_path, "--order-seed", "3")
    assert [t for t in whole if "gui/" not in t] != [t for t in default if "gui/" not in t]
