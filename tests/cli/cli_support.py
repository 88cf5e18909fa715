"""Shared inputs and checks of the command-line tests in tests/cli.

``demo_outputs`` builds, once per test session, the files ``unwind demo`` leaves behind, from the same phantom
and faster (seconds instead of half a minute): the tank scan ``tank.zarr``, the session ``fish_1.unwind.json``
made from the first fish's true centreline, the straight fish ``fish_1.zarr`` and the segmentation ``feat.zarr``.
``demo_copy`` copies them into a folder of a test's own (its session then points at the copied scan), for tests
that must be able to damage their inputs.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

UNWIND = Path(sys.executable).with_name("unwind")

#: A progress line written to a log (stderr not a terminal): ``write: 100% (12/12) in 3.4 s``.
PROGRESS_LINE = re.compile(r"^[^\r]+: (\d+% \(\d+/\d+\)|\d+ steps|done) in \d+\.\d s(, stopped)?$")


@dataclass(frozen=True)
class Demo:
    dir: Path
    tank: Path
    session: Path
    fish: Path
    feat: Path
    point: str  # "a0,a1,a2": a point inside fish 1, full-resolution voxels (the 75,36,43)
    scan_shape: tuple


_CACHE: dict[str, Demo] = {}


def demo_outputs(tmp_path_factory) -> Demo:
    """The demo's outputs (built once per test session)."""
    if "demo" not in _CACHE:
        _CACHE["demo"] = _build(tmp_path_factory.mktemp("demo"))
    return _CACHE["demo"]


def _build(folder: Path) -> Demo:
    from napari_unwind.datasets import tank_phantom
    from napari_unwind.demo import true_deformation
    from napari_unwind.io import open_volume, write_volume
    from napari_unwind.segmentation import save_features, segment
    from napari_unwind.session import Session, SourceInfo, save_session
    from napari_unwind.warp import export

    tank = tank_phantom(n_fish=2, seed=0)
    scan = write_volume(tank.volume, folder / "tank.zarr", spacing=tank.spacing, unit=tank.unit)
    fish = tank.fish[0]
    d = true_deformation(fish)
    session = save_session(Session(source=SourceInfo.from_path(scan), deformation=d), folder / "fish_1.unwind.json")
    straight = export(open_volume(scan), d, folder / "fish_1.zarr")
    feat = save_features(segment(open_volume(scan), features=5), folder / "feat.zarr")
    mid = fish.centerline[len(fish.centerline) // 2]
    return Demo(folder, Path(scan), Path(session), Path(straight), Path(feat),
                ",".join(f"{v:.1f}" for v in mid), tuple(tank.volume.shape))


def demo_copy(demo: Demo, folder: Path) -> Demo:
    """A copy of the demo's outputs in ``folder``, its session pointing at the copied scan."""
    for p in (demo.tank, demo.fish, demo.feat):
        shutil.copytree(p, folder / p.name)
    doc = json.loads(demo.session.read_text())
    doc["source"]["path"] = str(folder / demo.tank.name)
    (folder / demo.session.name).write_text(json.dumps(doc))
    return Demo(folder, folder / demo.tank.name, folder / demo.session.name, folder / demo.fish.name,
                folder / demo.feat.name, demo.point, demo.scan_shape)


def tree_hash(*paths: Path) -> str:
    """One hash of the names and bytes of every file under ``paths`` (files or folders)."""
    h = hashlib.sha256()
    for root in paths:
        root = Path(root)
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for f in files:
            h.update(str(f.relative_to(root.parent)).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()


def leftovers(*folders: Path) -> list[Path]:
    """Temporary outputs of atomic writes (``*.unwind-tmp``) anywhere under ``folders``.

    Read with ``os.walk``, which passes over a folder that vanishes while it is read: a test watches these while a
    process writes and removes them (``Path.rglob`` raised FileNotFoundError there once, on a loaded machine)."""
    return [Path(root) / name for f in folders for root, dirs, files in os.walk(f) for name in (*dirs, *files)
            if "unwind-tmp" in name]


def run(*args, cwd: Path | None = None, timeout: float = 120) -> tuple[int, str, str]:
    """``unwind ARGS...`` in a subprocess (optionally in ``cwd``); returns (exit status, stdout, stderr)."""
    r = subprocess.run([str(UNWIND), *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=timeout,
                       env={**os.environ, "PYTHONWARNINGS": ""})
    return r.returncode, r.stdout, r.stderr


def run_many(cases: list[tuple[list, Path | None]], timeout: float = 300) -> list[tuple[int, str, str]]:
    """Run several ``unwind`` commands at once, each ``(args, cwd)``; their (status, stdout, stderr) in order.

    The interpreter's start (a few seconds) is paid once in wall time rather than once per command.
    """
    env = {**os.environ, "PYTHONWARNINGS": ""}
    procs = [subprocess.Popen([str(UNWIND), *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True, cwd=cwd, env=env) for args, cwd in cases]
    results = []
    for p in procs:
        out, err = p.communicate(timeout=timeout)
        results.append((p.returncode, out, err))
    return results


def run_main(argv: list, capsys) -> tuple[int, str, str]:
    """``napari_unwind.cli.main(argv)`` in this process (an escaping exception fails the test)."""
    from napari_unwind.cli import main

    capsys.readouterr()
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def error_lines(err: str) -> list[str]:
    """The lines of stderr that are neither progress lines nor ``unwind: warning:`` lines."""
    return [ln for ln in err.splitlines()
            if ln.strip() and not PROGRESS_LINE.match(ln) and not ln.startswith("unwind: warning: ")]


def one_error_line(err: str) -> bool:
    """stderr holds exactly one error line, ``unwind: error: ...``, and no traceback (progress lines aside)."""
    lines = error_lines(err)
    return len(lines) == 1 and lines[0].startswith("unwind: error: ") and "Traceback" not in err
