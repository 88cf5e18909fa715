"""Reports shared by the command line and the demo: sizes, the ``unwind info`` text, progress to the end.

Below both :mod:`napari_unwind.cli` and :mod:`napari_unwind.demo`, so neither imports the other for them.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .progress import progress_bar, run

__all__ = ["describe", "disk_usage", "fmt_triple", "human_bytes", "run_with_bar"]


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(n) < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} TiB"  # pragma: no cover


def disk_usage(path: Path) -> int:
    """Bytes a file or folder tree takes on disk (apparent size)."""
    if path.is_file():
        return path.stat().st_size
    total = 0
    for root, _dirs, files in os.walk(path):
        for f in files:
            try:
                total += (Path(root) / f).stat().st_size
            except OSError:
                pass
    return total


def run_with_bar(gen: Any, quiet: bool) -> Any:
    """Run a progress generator to its end with :func:`~napari_unwind.progress.progress_bar`; its result."""
    callback, close = progress_bar(quiet)
    try:
        return run(gen, callback)
    finally:
        close()


def fmt_triple(values: Sequence[float]) -> str:
    return " x ".join(f"{v:g}" for v in values)


def describe(volume: Any, path: Path | None = None) -> str:
    """The ``unwind info`` report of a volume, as text."""
    unit = volume.unit_abbreviation
    lines = [
        f"path:      {volume.source or path}",
        f"format:    {volume.format}",
        f"shape:     {fmt_triple(volume.shape)}  (axis0 x axis1 x axis2)",
        f"dtype:     {volume.dtype}",
        f"spacing:   {fmt_triple(volume.spacing)} {unit}" + ("" if volume.unit else "  (unit not recorded)"),
        f"origin:    {fmt_triple(volume.origin)} {unit}",
        f"extent:    {fmt_triple([n * s for n, s in zip(volume.shape, volume.spacing, strict=True)])} {unit}",
        f"in memory: {human_bytes(volume.nbytes)}",
    ]
    if path is not None:
        lines.append(f"on disk:   {human_bytes(disk_usage(path))}")
    # from the header (Volume.level_shapes, level_chunks): the voxels' dask arrays are not built for a report
    shapes, level_chunks = volume.level_shapes, volume.level_chunks
    lines.append(f"levels:    {len(shapes)}")
    for i, (shape, lvl_chunks, sp) in enumerate(zip(shapes, level_chunks, volume.level_spacings, strict=True)):
        chunks = "x".join(str(c[0]) for c in lvl_chunks)
        lines.append(f"  {i}: {fmt_triple(shape):<22} spacing {fmt_triple(sp):<16} chunks {chunks}")
    return "\n".join(lines)
