"""The ``unwind`` command line: a thin face over the core.

Every subcommand parses its options, calls one core function (driving its progress generator with a bar) and
prints a short report. A user's mistake prints one clear ``unwind: error: ...`` line and exits 1; a traceback
means a bug.

Exit status: 0 success; 1 an error, a wrong option included (one line ``unwind: error: ...``); 3 (``unwind
run``, ``run --server``, ``submit --wait``, ``submit --batch`` and ``jobs watch``) a specimen straightened only in
part (:data:`napari_unwind.pipeline.EXIT_PARTIAL`); 130 interrupted
(Ctrl-C, SIGINT); 143 terminated (SIGTERM), 129 hung up (SIGHUP). Interrupted or terminated, no partial output
is left behind. Before any work, every command refuses an output that is, contains or lies inside one of its
inputs.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import re
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ._cliargs import (  # noqa: F401 (parse_size and the checks are part of this module's interface)
    DASH_VALUE_OPTIONS,
    _address,
    _arg_point,
    _check_io,
    _check_session_path,
    _chunks,
    _default_session_path,
    _endpoints_from_args,
    _export_options,
    _finite,
    _non_negative,
    _number,
    _pipeline_options,
    _positive,
    _reader_options,
    _series,
    _skeleton_options,
    _spacing3,
    _triple,
    _whole,
    join_dash_values,
    option_strings,
    parse_size,
)
from ._report import describe, disk_usage, human_bytes
from ._report import fmt_triple as _fmt_triple
from ._report import run_with_bar as _run_with_bar
from .errors import UnwindError, source_date_epoch

__all__ = ["main", "build_parser", "parse_size"]

EPILOG = """exit status: 0 success; 1 an error, a wrong option included (one line "unwind: error: ..."); 130
interrupted (Ctrl-C); 143 terminated (SIGTERM); 129 hung up (SIGHUP). Outputs are written atomically: an
interrupted run leaves no partial output, an existing output is replaced only with --overwrite, and an output
that is, contains or lies inside an input is refused."""

RUN_EPILOG = """status of a specimen: ok (straightened to the goals: at least 99 % of the mask inside the cage, no
lost interval, no fold over it), partial (written, but short of a goal: the reason is printed), failed, rejected
(--all: a feature that is not a specimen, with its reason in specimens.csv), unresolved (--all: a curved or coiled
body among other elongated ones, which may be two touching at an angle: not written; select it). Exit status: 0
when every specimen is ok; 3 when one is partial or unresolved (and none failed); 1 when one failed, on any error,
or when --all finds nothing specimen-like; 130 interrupted (Ctrl-C); 143 terminated (SIGTERM); 129 hung up (SIGHUP)."""


# ------------------------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------------------------




























def _check_output(path: str, overwrite: bool) -> None:
    """Check up front that an image output can be written (its format from the suffix, its folder, no file there
    unless overwriting), so that a mistake shows before the work instead of after it."""
    from .io._atomic import check_writable
    from .io._formats import output_format

    if output_format(path) != "stack":  # a slice pattern's folder is checked by its writer
        check_writable(path, overwrite=overwrite)


def _max_output(args: argparse.Namespace) -> dict[str, Any]:
    """``max_output=...`` for the warp functions when ``--max-output`` was given (else the library's default)."""
    return {"max_output": args.max_output} if hasattr(args, "max_output") else {}




# ------------------------------------------------------------------------------------------------------------------
# subcommands
# ------------------------------------------------------------------------------------------------------------------
def cmd_info(args: argparse.Namespace) -> int:
    from .io._headers import read_header

    path = Path(args.path)
    options = _reader_options(args, path)
    # the header alone, without numpy (issue 18: start in <= 0.3 s); None for any other format and anything
    # unusual, which the full reader opens (and reports, warns about or refuses)
    header = read_header(path, **options)
    if header is None and "channel" not in options and _channel_count(str(path), args) > 1:
        from .io import open_channels

        chans = open_channels(path, **options)
        names = [str(c.metadata["channel"]) for c in chans]
        print(describe(chans[0], path))
        print(f"channels:  {len(chans)} ({', '.join(names)}), each as above; one with --input-channel NAME")
        return 0
    if header is None:
        from .io import open_volume

        header = open_volume(path, **options)
    print(describe(header, path))
    return 0


def cmd_import(args: argparse.Namespace) -> int:
    from .io import import_volume_iter, open_volume

    _check_io([args.output], [args.input])
    reader = _reader_options(args, args.input)
    if "channel" not in reader and _channel_count(args.input, args) > 1:
        if args.labels or args.nan_value is not None or args.spacing is not None or args.unit is not None:
            raise UnwindError(f"{args.input} has several channels: --labels, --nan-value, --spacing and --unit import "
                              "one channel at a time (--input-channel NAME)")
        from .io import open_channels, write_channels_iter

        chans = open_channels(args.input, **reader)
        t0 = time.perf_counter()
        written = _run_with_bar(write_channels_iter(chans, args.output, format="ome-zarr", overwrite=args.overwrite,
                                                    max_side=args.max_side,
                                                    **({} if args.chunks is None else {"chunks": args.chunks})),
                                args.quiet)
        if not args.quiet:
            print(f"imported {args.input} -> {written}: {len(chans)} channels "
                  f"({', '.join(c.metadata['channel'] for c in chans)}) in {time.perf_counter() - t0:.1f} s")
        return 0
    src = open_volume(args.input, **reader)
    t0 = time.perf_counter()
    result = _run_with_bar(
        import_volume_iter(src, args.output, chunks=args.chunks, max_side=args.max_side, overwrite=args.overwrite,
                           nan_value=args.nan_value, spacing=args.spacing, unit=args.unit, labels=args.labels),
        args.quiet,
    )
    dt = time.perf_counter() - t0
    if not args.quiet:
        print(f"imported {args.input} -> {args.output} in {dt:.1f} s "
              f"({human_bytes(src.nbytes / max(dt, 1e-9))}/s)")
        print(describe(result, Path(args.output)))
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    from .io import open_volume, write_volume_iter

    _check_io([args.output], [args.input])
    reader = _reader_options(args, args.input)
    if "channel" not in reader and _channel_count(args.input, args) > 1:
        return _convert_channels(args, reader)
    src = open_volume(args.input, **reader)
    if args.level is not None:
        if not 0 <= args.level < len(src.levels):
            raise UnwindError(f"{args.input} has pyramid levels 0..{len(src.levels) - 1}, got --level {args.level}")
        src = src.with_data(src.levels[args.level], spacing=src.level_spacings[args.level])
    options: dict[str, Any] = {}
    if args.chunks is not None:
        options["chunks"] = args.chunks
    t0 = time.perf_counter()
    written = _run_with_bar(
        write_volume_iter(src, args.output, spacing=args.spacing, unit=args.unit, format=args.format,
                          overwrite=args.overwrite, nan_value=args.nan_value, **options),
        args.quiet,
    )
    if not args.quiet:
        print(f"wrote {written} ({human_bytes(disk_usage(Path(written)))}) in {time.perf_counter() - t0:.1f} s")
    return 0


def _convert_channels(args: argparse.Namespace, reader: dict[str, Any]) -> int:
    """``unwind convert`` of a scan with a channel axis: every channel, into one multi-channel image."""
    from .io import open_channels, write_channels_iter

    if args.level is not None or args.nan_value is not None or args.spacing is not None or args.unit is not None:
        raise UnwindError(f"{args.input} has several channels: --level, --nan-value, --spacing and --unit convert one "
                          "channel at a time (--input-channel NAME)")
    chans = open_channels(args.input, **reader)
    options: dict[str, Any] = {} if args.chunks is None else {"chunks": args.chunks}
    t0 = time.perf_counter()
    written = _run_with_bar(write_channels_iter(chans, args.output, format=args.format, overwrite=args.overwrite,
                                                **options), args.quiet)
    if not args.quiet:
        print(f"wrote {written}: {len(chans)} channels ({', '.join(c.metadata['channel'] for c in chans)}), "
              f"{human_bytes(disk_usage(Path(written)))} in {time.perf_counter() - t0:.1f} s")
    return 0


def _load_session_for(args: argparse.Namespace, input_path: str | None, outputs: Sequence[Any] = (),
                      inputs: Sequence[Any] = ()):
    """Load ``--session``, refuse ``outputs`` over an input (``inputs``, the session and the session's source),
    then check the scan against the session's checksum (unless ``--no-verify``)."""
    from .progress import progress_bar
    from .session import load_session, verify_source

    session = load_session(args.session)
    if session.deformation is None:
        raise UnwindError(f"{args.session} holds no deformation yet; run the skeleton solve first (unwind skeleton)")
    _check_io(outputs, [*inputs, args.session, session.source.path])
    if input_path is not None and not args.no_verify:
        callback, close = progress_bar(args.quiet)
        try:
            verify_source(session, input_path, progress=callback)
        finally:
            close()
    return session


def _channel_count(path: str, args: argparse.Namespace) -> int:
    from .io._formats import detect_format
    from .io.channels import _count

    p = Path(path).expanduser().absolute()
    if not p.exists():
        return 1  # open_volume says it does not exist
    fmt = getattr(args, "input_format", None) or detect_format(p)
    return _count(p, fmt, {"series": args.series} if getattr(args, "series", None) is not None else {})


def _straighten_channels(args: argparse.Namespace) -> int:
    """``unwind straighten`` of several channels (several inputs, or one with a channel axis) into one image."""
    from dataclasses import replace

    from .io import open_channels
    from .pipeline import export_step
    from .session import SourceInfo

    _check_output(args.output, args.overwrite)
    options = _export_options(args)
    names = [n.strip() for n in args.channel_names.split(",")] if args.channel_names else None
    # without --same-grid the first input is the session's scan (checked against its checksum); the others are
    # images of its grid (shape here; spacing and origin by the warp)
    session = _load_session_for(args, None if args.same_grid else args.input[0], [args.output], args.input)
    first_opts = _reader_options(args, args.input[0])
    channels = open_channels(args.input, names=names, **first_opts)
    if len(channels) == 1:
        raise UnwindError(f"--channel-names names the channels of a multi-channel output, and {args.input[0]} has "
                          "one channel: leave the option out, or give the other channels' images after it")
    for v in channels:
        _check_same_grid(session, v, str(v.source))
    deformation = session.deformation
    # the session's scan itself (the first input, checked above, when it holds one channel) is its source already
    skip_first = not args.same_grid and _channel_count(args.input[0], args) == 1
    records, digests = [], {}
    for k, v in enumerate(channels):
        if k == 0 and skip_first:
            continue
        key = str(v.source)
        if key not in digests:
            digests[key] = SourceInfo.from_path(key, volume=v)
        records.append(replace(digests[key], channel=str(v.metadata["channel"]), dtype=str(v.dtype),
                               shape=tuple(v.shape)))
    embedded = replace(session, channels=(*session.channels, *records))
    t0 = time.perf_counter()
    # the core's one export step (its fold rule, its options' keywords): what unwind run and the server write
    written = _run_with_bar(export_step(channels[0], deformation, args.output, options=options, session=embedded,
                                        overwrite=args.overwrite, scheduler=args.scheduler, channels=channels[1:]),
                            args.quiet)
    if not args.quiet:
        print(f"straightened {len(channels)} channels ({', '.join(v.metadata['channel'] for v in channels)}) -> "
              f"{written} in {time.perf_counter() - t0:.1f} s")
        print(f"length {deformation.length:.4g} {channels[0].unit_abbreviation}, {len(deformation)} keyframes")
    return 0


def cmd_straighten(args: argparse.Namespace) -> int:
    from .io import open_volume
    from .pipeline import export_step

    if args.input_channel is not None and (len(args.input) > 1 or args.channel_names):
        raise UnwindError("--input-channel picks one channel of one scan; to straighten several images together "
                          "leave it out")
    if args.input_channel is None and (len(args.input) > 1 or args.channel_names
                                       or _channel_count(args.input[0], args) > 1):
        return _straighten_channels(args)
    args.input = args.input[0]
    _check_output(args.output, args.overwrite)
    options = _export_options(args)
    session = _load_session_for(args, None if args.same_grid else args.input, [args.output], [args.input])
    volume = open_volume(args.input, **_reader_options(args, args.input))
    if args.same_grid:
        _check_same_grid(session, volume, args.input)
    deformation = session.deformation
    embedded = session
    if args.same_grid:  # the output's own session records the image it was made from
        from dataclasses import replace

        from .session import SourceInfo

        embedded = replace(session, channels=(*session.channels, SourceInfo.from_path(args.input, volume=volume)))
    t0 = time.perf_counter()
    # the core's one export step (its fold rule, its options' keywords): what unwind run and the server write
    written = _run_with_bar(export_step(volume, deformation, args.output, options=options, session=embedded,
                                        overwrite=args.overwrite, scheduler=args.scheduler), args.quiet)
    if not args.quiet:
        out = open_volume(written)
        print(f"straightened {args.input} -> {written} in {time.perf_counter() - t0:.1f} s")
        print(f"shape {_fmt_triple(out.shape)} (s x y x x), spacing {_fmt_triple(out.spacing)} "
              f"{out.unit_abbreviation}, length {deformation.length:.4g} {out.unit_abbreviation}, "
              f"{len(deformation)} keyframes")
    return 0


def _channel_arg(text: str) -> tuple[str, str]:
    """``NAME=PATH`` or ``PATH`` (named by its file name) for ``unwind measure --channel``."""
    name, sep, path = text.partition("=")
    if not sep:
        path = text
        name = Path(text).name.split(".")[0] or "intensity"
    if not name or not path:
        raise argparse.ArgumentTypeError(f"takes NAME=PATH or PATH, got {text!r}")
    return name, path


def cmd_measure(args: argparse.Namespace) -> int:
    from .io import open_volume
    from .io._atomic import check_writable
    from .measure import _need, measure_iter, profile_format

    kind = profile_format(args.output, formats=(".csv", ".parquet"))
    if kind == ".parquet":
        _need("pyarrow", "tables", "Parquet")
    if args.plot is not None:
        if Path(args.plot).suffix.lower() != ".png":
            raise UnwindError(f"the plot is written as PNG: give --plot a path ending in .png, got {args.plot}")
        _need("matplotlib", "plot", "the plot")
    outputs = [x for x in (args.output, args.plot) if x is not None]
    for out in outputs:
        check_writable(out, overwrite=args.overwrite)
    session = _load_session_for(args, None, outputs,
                                [x for x in (args.mask, args.labels, *[c for _, c in args.channel]) if x])
    seg = session.segmentation
    if args.mask_label is not None and not args.mask:
        raise UnwindError("--mask-label picks a label of --mask MASK: give the mask too (the session's own mask "
                          "file is read with the label it recorded)")
    mask_path = args.mask or (seg.mask if seg is not None else None)
    if mask_path is None and not args.quiet:
        print("note: no mask (the session's selection was not a mask file; give --mask): no cross-section columns",
              file=sys.stderr)
    mask = None
    if mask_path is not None:
        mask = open_volume(mask_path)
        label = args.mask_label if args.mask else (seg.mask_label if seg is not None else None)
        if label is not None:
            from .io import Volume
            from .pipeline import pick_mask_label

            mask = Volume(pick_mask_label(mask.data, label).astype("uint8"), spacing=mask.spacing,
                          origin=mask.origin, unit=mask.unit)
    notes: list[str] = []
    if mask is not None:
        mask = _on_session_grid(mask, session, "mask", notes)
        if label is None:
            from .pipeline import _labels_note

            notes += [n for n in (_labels_note(mask.data),) if n]
    channels = {}
    for name, path in args.channel:
        if name in channels:
            raise UnwindError(f"two channels are named {name!r}: name them with --channel NAME=PATH")
        channels[name] = open_volume(path)
    labels = _on_session_grid(open_volume(args.labels), session, "label image", notes) if args.labels else None
    _warn_lines(notes)
    t0 = time.perf_counter()
    profile = _run_with_bar(measure_iter(session.deformation, mask=mask, labels=labels, channels=channels or None,
                                         spacing=args.spacing), args.quiet)
    if kind == ".parquet":  # provenance in the schema's metadata (the CSV stays the server's bytes)
        from dataclasses import replace

        profile = replace(profile, meta={"session": str(args.session), "mask": str(mask_path or ""),
                                         "labels": str(args.labels or ""), "spacing": str(args.spacing or ""),
                                         "channels": ";".join(f"{n}={c}" for n, c in args.channel)})
    written = profile.save(args.output, overwrite=args.overwrite)
    if args.plot is not None:
        profile.plot(args.plot, overwrite=args.overwrite)
    if not args.quiet:
        print(f"measured {len(profile)} stations ({len(profile.columns)} columns) in "
              f"{time.perf_counter() - t0:.1f} s -> {written}" + (f", {args.plot}" if args.plot else ""))
    return 0


def _on_session_grid(volume: Any, session: Any, what: str, notes: list[str]) -> Any:
    """:meth:`~napari_unwind.session.Session.on_scan_grid`, its note added to ``notes``."""
    volume, note = session.on_scan_grid(volume, what)
    if note:
        notes.append(note)
    return volume


def _check_same_grid(session: Any, volume: Any, path: str) -> None:
    """``--same-grid``: another image of the session's scan grid (a channel, a stain) has its shape; its spacing and
    origin are compared with the deformation's by the warp itself."""
    src = session.source
    if tuple(volume.shape) != tuple(src.shape):
        raise UnwindError(f"{path} has shape {_fmt_triple(volume.shape)}, the session's scan "
                          f"{_fmt_triple(src.shape)}: --same-grid takes images of the scan's own grid")


#: What ``unwind average`` takes from a folder: straight volumes in these formats.
_STRAIGHT_SUFFIXES = (".ome.zarr", ".zarr", ".nrrd", ".nhdr", ".nii", ".nii.gz", ".tif", ".tiff")


def _average_inputs(items: Sequence[str]) -> list[Path]:
    found: list[Path] = []
    for item in items:
        path = Path(item)
        if path.name.endswith(".unwind.json"):
            raise UnwindError(f"{item} is a session: straighten it first (unwind straighten SCAN --session {item} -o "
                              "straight.ome.zarr) and average the straight volumes")
        if path.is_dir() and not path.name.endswith(".zarr"):
            inside = sorted(p for p in path.iterdir()
                            if p.name.lower().endswith(_STRAIGHT_SUFFIXES) and not p.name.startswith("."))
            if not inside:
                raise UnwindError(f"{item} holds no straight volume ({', '.join(_STRAIGHT_SUFFIXES)})")
            found += inside
        elif not path.exists():
            raise UnwindError(f"{item} does not exist")
        else:
            found.append(path)
    return found


def _sibling(output: Path, what: str) -> Path:
    """``mean.ome.zarr`` -> ``mean.median.ome.zarr``: the other outputs of ``unwind average`` beside the mean."""
    name = output.name
    for suffix in sorted(_STRAIGHT_SUFFIXES, key=len, reverse=True):
        if name.lower().endswith(suffix):
            return output.with_name(f"{name[: -len(suffix)]}.{what}{name[-len(suffix):]}")
    return output.with_name(f"{name}.{what}")


def cmd_average(args: argparse.Namespace) -> int:
    import numpy as np

    from .average import average_iter, read_landmarks
    from .io import write_volume
    from .io._atomic import check_writable
    from .pipeline import _write_table

    inputs = _average_inputs(args.inputs)
    out = Path(args.output)
    if not out.name.lower().endswith(_STRAIGHT_SUFFIXES):
        raise UnwindError(f"the average is written beside its median and std: give an output ending in one of "
                          f"{', '.join(_STRAIGHT_SUFFIXES)}, got {args.output}")
    _check_output(str(out), args.overwrite)
    others = {what: _sibling(out, what) for what in ("median", "std")}
    stem = _sibling(out, "residuals").name
    table = out.with_name(stem[: stem.index(".residuals")] + ".residuals.csv")
    for p in (*others.values(), table):
        check_writable(p, overwrite=args.overwrite)
    _check_io([out, *others.values(), table], inputs)
    t0 = time.perf_counter()
    landmarks = read_landmarks(args.landmarks, inputs) if args.landmarks else None
    res = _run_with_bar(average_iter([str(p) for p in inputs], stations=args.stations, landmarks=landmarks,
                                     scale=args.scale, normalise=args.normalise, max_roll=args.max_roll,
                                     scheduler=args.scheduler), args.quiet)
    spacing = (res.spacing,) * 3
    write_volume(res.mean, out, spacing=spacing, unit=res.unit, overwrite=args.overwrite)
    for what, path in others.items():
        write_volume(getattr(res, what), path, spacing=spacing, unit=res.unit, overwrite=args.overwrite)
    rows = res.table()
    _write_table(rows, table, list(rows[0]), overwrite=args.overwrite)
    if not args.quiet:
        worst = int(np.argmin(res.correlation))
        print(f"averaged {len(inputs)} specimens -> {out} (and {', '.join(p.name for p in others.values())}, "
              f"{table.name}) in {time.perf_counter() - t0:.1f} s; shape {_fmt_triple(res.mean.shape)}; least "
              f"like the mean: {res.names[worst]} (correlation {res.correlation[worst]:.3f})")
    return 0


def cmd_bend(args: argparse.Namespace) -> int:
    from types import SimpleNamespace

    from .io import open_volume, write_volume_iter
    from .warp import _check_geometry, bend

    _check_output(args.output, args.overwrite)
    session = _load_session_for(args, None, [args.output], [args.input])
    src = session.source
    # the bent volume lies on the deformation's grid: bend(scan=...) refuses a scan whose grid is not the
    # deformation's, as straighten does; without the scan at hand (moved, or it needs reader options), the spacing
    # and unit the session recorded are checked the same way, and the session's shape is the output's
    straight = open_volume(args.input, **_reader_options(args, args.input))
    shape = tuple(src.shape)
    options = dict(order=args.order, chunks=args.chunks, **_max_output(args))
    try:
        scan: Any = open_volume(src.path)
    except (OSError, UnwindError):
        scan = None
    if scan is not None:
        data = bend(straight, session.deformation, scan=scan, shape=shape, **options)
        unit = session.deformation.unit or scan.unit
    else:
        recorded = SimpleNamespace(spacing=src.spacing, unit=src.unit, origin=session.deformation.origin)
        unit = _check_geometry(recorded, session.deformation)
        data = bend(straight, session.deformation, shape=shape, **options)
    t0 = time.perf_counter()
    written = _run_with_bar(
        write_volume_iter(data, args.output, spacing=session.deformation.spacing,
                          origin=session.deformation.origin, unit=unit, overwrite=args.overwrite),
        args.quiet,
    )
    if not args.quiet:
        print(f"bent {args.input} into the pose of {src.path} -> {written} "
              f"({_fmt_triple(shape)}) in {time.perf_counter() - t0:.1f} s")
    return 0


def _read_points(args: argparse.Namespace):
    """The points of ``map-points``: ``--at`` (repeatable) or a points file
    (:func:`napari_unwind.io.points.read_points`), never both."""
    import numpy as np

    if args.at and args.points:
        raise UnwindError(f"give points with --at or a file, not both (got --at and {args.points})")
    if args.at:
        return np.array(args.at, dtype=float)
    if not args.points:
        raise UnwindError("give points with --at A0,A1,A2 (repeatable) or a CSV file of 3 columns")
    from .io.points import read_points

    return read_points(args.points)


def cmd_map_points(args: argparse.Namespace) -> int:
    import numpy as np

    from .io._atomic import atomic_output
    from .warp import map_points

    pts = _read_points(args)  # a mistake in the points is told before the session is read
    session = _load_session_for(args, None, [args.output], [args.points])
    mapped = map_points(pts, session.deformation, to=args.to, spacing=args.spacing)
    header = "axis0,axis1,axis2" if args.to == "scan" else "s_index,y_index,x_index"
    lines = [f"# {'scan' if args.to == 'straight' else 'straight'} -> {args.to} voxels; NaN: outside the cage",
             header] + [",".join("nan" if not np.isfinite(v) else f"{v:.6g}" for v in row) for row in mapped]
    text = "\n".join(lines) + "\n"
    if args.output:
        with atomic_output(args.output, overwrite=args.overwrite) as tmp:
            tmp.write_text(text)
        if not args.quiet:
            print(f"wrote {len(mapped)} points to {args.output}")
    else:
        sys.stdout.write(text)
    return 0


def cmd_segment(args: argparse.Namespace) -> int:
    from .io import open_volume
    from .segmentation import candidates, check_segmentation_output, save_features_iter, segment_iter

    check_segmentation_output(args.output, overwrite=args.overwrite)  # before minutes of work, not after
    _check_io([args.output], [args.input])
    volume = open_volume(args.input, **_reader_options(args, args.input))
    t0 = time.perf_counter()
    features = _run_with_bar(segment_iter(volume, features=args.features, level=args.level, smooth=args.smooth),
                             args.quiet)
    dt = time.perf_counter() - t0
    written = _run_with_bar(save_features_iter(features, args.output, overwrite=args.overwrite), args.quiet)
    every = candidates(features)
    found = [c for c in every if c.is_specimen]
    unresolved = [c for c in every if c.status == "unresolved"]  # a click must say (pipeline.STATUSES)
    specimen_ids = {i for c in found if not c.unclaimed for i in c.ids}
    unresolved_ids = {i for c in unresolved if not c.unclaimed for i in c.ids}
    if args.specimens and args.quiet:  # for scripts: the specimens' names (a feature id, or "3.1" for a part)
        print(",".join(c.name for c in found))
    if not args.quiet:
        print(f"segmented {args.input} at level {features.level} ({_fmt_triple(features.shape)}) into "
              f"{features.k} features in {dt:.1f} s -> {written}")
        print(f"{'id':>4} {'voxels':>9} {'values':>17} {'bounding box (full-resolution voxels)':>40} "
              f"{'elongation':>10}  kind")
        rows = [(c.name, c.stats, "specimen") for c in found] if args.specimens else [
            (str(st.id), st, "specimen" if st.id in specimen_ids else "unresolved" if st.id in unresolved_ids
             else "container" if st.container else "-")
            for st in features.stats]
        for name, st, kind in rows:
            box = st.bbox_full
            print(f"{name:>4} {st.voxel_count:>9} {st.value_min:>8.4g}-{st.value_max:<8.4g} "
                  f"{box[0]:>6}:{box[3]:<6} {box[1]:>6}:{box[4]:<6} {box[2]:>6}:{box[5]:<6} "
                  f"{st.elongation:>10.2f}  {kind}")
        print(f"{len(found)} specimen(s) (elongated, inside the scan, not containers): "
              f"{', '.join(c.name for c in found) or 'none'}")
        for c in unresolved:
            print(f"unresolved {c.name}: {c.reason}")
        for c in found:
            if c.reason:
                print(f"  {c.name}: {c.reason}")
        print("pick features with: unwind select LABELS --at A0,A1,A2 -o MASK (points in full-resolution voxels)")
    return 0


def cmd_select(args: argparse.Namespace) -> int:
    from .io import open_volume, write_volume_iter
    from .segmentation import load_features, refine_mask_iter, select

    if not args.at and not args.id:
        raise UnwindError("choose features with --at A0,A1,A2 (a point inside one) or --id N (repeatable)")
    _check_io([args.output], [args.labels, args.full_resolution])
    features = load_features(args.labels)
    mask = select(features, seeds=args.at, ids=args.id, fill_holes=args.fill_holes)
    if args.full_resolution:
        volume = open_volume(args.full_resolution, **_reader_options(args, args.full_resolution))
        written = _run_with_bar(
            refine_mask_iter(volume, mask, features=features, isovalue=args.isovalue, output=args.output,
                             overwrite=args.overwrite),
            args.quiet,
        )
        where = f"full resolution {_fmt_triple(volume.shape)}"
    else:
        if args.isovalue is not None:
            raise UnwindError("--isovalue refines at full resolution: give the scan with --full-resolution INPUT")
        written = _run_with_bar(
            write_volume_iter(mask.astype("uint8"), args.output, spacing=features.spacing, unit=features.unit,
                              origin=features.working_origin, overwrite=args.overwrite,
                              **({"labels": True} if str(args.output).rstrip("/").endswith(".zarr") else {})),
            args.quiet,
        )
        where = f"working resolution {_fmt_triple(mask.shape)}"
    if not args.quiet:
        print(f"selected {int(mask.sum())} working voxels -> {written} ({where})")
    return 0


# ------------------------------------------------------------------------------------------------------------------
# skeleton solve and the whole pipeline
# ------------------------------------------------------------------------------------------------------------------
def _fmt_point(p: Sequence[float]) -> str:
    return "(" + ", ".join(f"{float(v):.1f}" for v in p) + ")"










def _mask_geometry(mask: Any, scan: Any) -> tuple[Any, list[str]]:
    """The mask on the deformation's grid: the scan's (a mask of its shape voxel for voxel, or a box of its grid
    placed by its origin: :func:`~napari_unwind.io._grid.place_on_grid`), or the mask's own without a scan."""
    if scan is None:
        return mask, []
    from .io._grid import place_on_grid

    placed, note = place_on_grid(mask, scan)
    return placed, [note] if note else []


def _estimate(mask_data: Any, endpoints: Any, *, spacing: Sequence[float], origin: Sequence[float],
              unit: str | None, volume: Any, args: argparse.Namespace) -> tuple[Any, list[str]]:
    """Run the skeleton solve (:func:`napari_unwind.pipeline.skeleton_step`) with a progress bar; returns the
    SkeletonResult and its warnings (one line each)."""
    from .pipeline import skeleton_step

    result = _run_with_bar(
        skeleton_step(mask_data, endpoints, spacing=spacing, origin=origin, unit=unit, volume=volume,
                      options=_skeleton_options(args)),
        args.quiet,
    )
    return result, list(result.warnings)


def _skeleton_report(result: Any, args: argparse.Namespace) -> list[str]:
    """The lines of the skeleton summary."""
    import numpy as np

    from .io._volume import unit_label

    d = result.deformation
    unit = unit_label(d.unit)
    he = d.half_extents
    if np.allclose(he, he[0]):
        cage = f"{he[0, 0]:.4g} x {he[0, 1]:.4g} {unit}"
    else:
        cage = (f"{he[:, 0].min():.4g}-{he[:, 0].max():.4g} x {he[:, 1].min():.4g}-{he[:, 1].max():.4g} {unit}")
    lines = [
        f"{len(d)} keyframes, length {d.length:.4g} {unit}, cage half extents (u x v) {cage}, padding "
        f"{d.pad[0]:.4g} / {d.pad[1]:.4g} {unit} (head / tail)",
    ]
    if args.no_twist:
        lines.append("twist: not estimated (--no-twist): frames by parallel transport")
    else:
        lines.append(result.twist_report())
    if result.context is not None:
        lines.append(f"context: {args.context:.4g} {unit} asked, at least {max(result.context, 0.0):.4g} {unit} "
                     "beyond the mask on every side")
    lines.append(result.report())
    total = sum(result.timings.values())
    lines.append("times: " + ", ".join(f"{k} {v:.2f} s" for k, v in result.timings.items()) + f" (total {total:.1f} s)")
    return lines


def _say_endpoints(result: Any, say: Callable[..., Any]) -> None:
    e = result.endpoints
    if result.suggested:
        say(f"suggested head: {_fmt_point(e.head)}, tail: {_fmt_point(e.tail)} (voxels, axis0,axis1,axis2); check "
            f"them, or give the ends: --head {_arg_point(e.head)} --tail {_arg_point(e.tail)}")
    else:
        say(f"head: {_fmt_point(e.head)}, tail: {_fmt_point(e.tail)} (voxels, after snapping into the mask)"
            + (f", {len(e.chain)} parts chained" if e.chain else ""))


def _warn_lines(messages: Sequence[str]) -> None:
    for m in messages:
        print(f"unwind: warning: {_one_line(m)}", file=sys.stderr)


def _source_info(path: str | os.PathLike, volume: Any, quiet: bool):
    from .progress import progress_bar
    from .session import SourceInfo

    callback, close = progress_bar(quiet)
    try:
        return SourceInfo.from_path(path, volume=volume, progress=callback)
    finally:
        close()


def cmd_skeleton(args: argparse.Namespace) -> int:
    from .io import open_volume
    from .session import Segmentation, Session, save_session

    target = _check_session_path(args.output, args.overwrite)
    _check_io([args.output], [args.mask, args.volume])
    endpoints = _endpoints_from_args(args)
    mask = open_volume(args.mask)
    scan = open_volume(args.volume, **_reader_options(args, args.volume)) if args.volume else None
    placed, notes = _mask_geometry(mask, scan)
    spacing, origin, unit, mask_data = placed.spacing, placed.origin, placed.unit, placed.data
    if args.mask_label is not None:
        from .pipeline import pick_mask_label

        mask_data = pick_mask_label(mask_data, args.mask_label)
    say = (lambda *a: None) if args.quiet else print
    t0 = time.perf_counter()
    result, messages = _estimate(mask_data, endpoints, spacing=spacing, origin=origin, unit=unit,
                                 volume=None if scan is None else scan.data, args=args)
    dt = time.perf_counter() - t0
    source_path, source_vol = (args.volume, scan) if scan is not None else (args.mask, mask)
    source = _source_info(source_path, source_vol, args.quiet)
    refined = (mask.metadata.get("unwind") or {}).get("refined_mask") if isinstance(mask.metadata, dict) else None
    iso = refined.get("isovalue") if isinstance(refined, dict) else None
    # the selection is the mask file (unwind measure and the dock find it again), at the isovalue that refined it
    segmentation = Segmentation(isovalue=iso, mask=str(Path(args.mask).absolute()), mask_label=args.mask_label)
    session = Session(source=source, deformation=result.deformation, segmentation=segmentation,
                      endpoints=result.endpoints, twist=result.twist_profile(),
                      notes=f"unwind skeleton: mask {Path(args.mask).absolute()}"
                            + ("; suggested endpoints" if result.suggested else ""))
    written = save_session(session, target, overwrite=args.overwrite)
    if result.deformation.folds():  # the skeleton's own warning says where; say what it means here
        messages.append("unwind straighten refuses a folding deformation without --allow-folds")
    _warn_lines(notes + messages)
    _say_endpoints(result, say)
    say(f"skeleton of {args.mask} in {dt:.1f} s -> {written}")
    for line in _skeleton_report(result, args):
        say(line)
    if scan is None:
        say(f"the session's source is the mask itself ({args.mask}, no --volume given): unwind straighten MASK "
            "--session ... straightens the mask; to straighten the scan, run again with --volume SCAN (or pass "
            "--no-verify to unwind straighten)")
    else:
        say(f"the session's source is the scan {args.volume}: unwind straighten {args.volume} --session {written} "
            "-o OUTPUT")
    from .pipeline import EXIT_PARTIAL, judge

    status, reason = judge(result)
    if status != "ok":  # the session is written, but it does not straighten the specimen to the goals
        print(f"unwind: {status}: {_one_line(reason)}", file=sys.stderr)
        return EXIT_PARTIAL
    return 0


def _say_results(results: Sequence[Any], say: Callable[..., Any]) -> None:
    """One line per specimen or candidate: ok and rejected on stdout, partial, unresolved and failed on stderr."""
    for r in results:
        if r.status == "failed":
            print(f"unwind: error: {r.name} failed: {_one_line(r.reason)}", file=sys.stderr)
        elif r.status in ("partial", "unresolved"):
            print(f"unwind: {r.status}: {_one_line(r.summary())}", file=sys.stderr)
        else:
            say(r.summary())


def _run_all(args: argparse.Namespace) -> int:
    """``unwind run SCAN --all -o OUTDIR``: every specimen, no click (:func:`napari_unwind.pipeline.run_all_iter`)."""
    from .pipeline import STATUSES, exit_status, run_all_iter

    clash = [name for name, given in (("--mask", args.mask), ("--select", args.select), ("--head", args.head),
                                      ("--tail", args.tail), ("--chain", args.chain), ("--session", args.session),
                                      ("--isovalue", args.isovalue is not None), ("--fill-holes", args.fill_holes),
                                      ("--server", getattr(args, "server", None))) if given]
    if clash:
        raise UnwindError(f"--all finds every specimen and its ends itself; it does not take {', '.join(clash)}")
    say = (lambda *a: None) if args.quiet else print
    options = _pipeline_options(args)
    _check_io([args.output], [args.input])
    result = _run_with_bar(
        run_all_iter(args.input, args.output, options=options, overwrite=args.overwrite,
                     reader_options=_reader_options(args, args.input)),
        args.quiet,
    )
    feats = result.features
    found = [r for r in result.specimens if r.status != "rejected"]
    unresolved = sum(r.status == "unresolved" for r in found)
    say(f"segmented {args.input} at level {feats.level} ({_fmt_triple(feats.shape)}) into {feats.k} features; "
        f"{len(found) - unresolved} specimen(s), " + (f"{unresolved} unresolved, " if unresolved else "")
        + f"{len(result.specimens) - len(found)} rejected")
    _say_results(result.specimens, say)
    if not found:
        print(f"unwind: error: nothing specimen-like found in {args.input}: every one of the {len(result.specimens)} "
              f"features was rejected (reasons in {result.table}); try more features (--features N), select the "
              "specimen (unwind run --select A0,A1,A2) or straighten a mask (unwind run --mask)", file=sys.stderr)
        return 1
    counts = {s: sum(r.status == s for r in result.specimens) for s in STATUSES}
    say(f"summary -> {result.table} ({counts['ok']} straightened, {counts['partial']} partial, {counts['failed']} "
        f"failed, " + (f"{counts['unresolved']} unresolved (select them: --select A0,A1,A2), "
                       if counts["unresolved"] else "") + f"{counts['rejected']} rejected) in {result.seconds:.1f} s")
    return exit_status(result.specimens)


def cmd_run(args: argparse.Namespace) -> int:
    if getattr(args, "all", False):
        return _run_all(args)
    if getattr(args, "server", None):
        from ._cli_remote import run_remote

        return run_remote(args)
    from .io import open_volume
    from .pipeline import exit_status, run_iter

    if args.mask and args.select:
        raise UnwindError("give either --mask MASK or --select A0,A1,A2 (segmentation), not both")
    if not args.mask and not args.select:
        raise UnwindError("say which specimen to straighten: --select A0,A1,A2 (a point inside it, full-resolution "
                          "voxels; the scan is segmented first) or --mask MASK (a mask from unwind select)")
    if args.mask_label is not None and not args.mask:
        raise UnwindError("--mask-label picks a label of --mask MASK: give the mask too")
    if args.mask and (args.features is not None or args.fill_holes or args.isovalue is not None
                      or args.level is not None):
        raise UnwindError("--features, --level, --isovalue and --fill-holes choose the segmentation; they do not "
                          "apply with --mask")
    options = _pipeline_options(args)
    _check_output(args.output, args.overwrite)
    session_path = Path(args.session) if args.session else _default_session_path(args.output)
    target = _check_session_path(session_path, args.overwrite)
    _check_io([args.output, session_path], [args.input, args.mask])
    endpoints = _endpoints_from_args(args)
    say = (lambda *a: None) if args.quiet else print
    t_all = time.perf_counter()

    volume = open_volume(args.input, **_reader_options(args, args.input))
    notes: list[str] = []
    mask = None
    if args.mask:
        mask_vol = open_volume(args.mask)
        placed, notes = _mask_geometry(mask_vol, volume)
        mask = placed.data
        if args.mask_label is not None:
            from .pipeline import check_mask_label

            check_mask_label(mask, args.mask_label)  # before the checksum and the solve
    source = _source_info(args.input, volume, args.quiet)
    result = _run_with_bar(
        run_iter(volume, mask=mask, seeds=args.select, endpoints=endpoints, options=options, output=args.output,
                 session_path=target, source=source, overwrite=args.overwrite, mask_source=args.mask,
                 mask_label=args.mask_label,
                 notes="unwind run" + (f": mask {Path(args.mask).absolute()}" if args.mask else "")),
        args.quiet,
    )
    _warn_lines(notes + list(result.warnings))
    seg = result.session.segmentation
    if seg is not None and seg.mask is None:
        say(f"segmented {args.input} at level {seg.level} into {seg.k} features; selected feature"
            f"{'s' if len(seg.selected) > 1 else ''} {', '.join(map(str, seg.selected))} under "
            f"{', '.join(_fmt_point(p) for p in seg.seeds)}, refined at full resolution (isovalue {seg.isovalue:.4g})")
    _say_endpoints(result.skeleton, say)
    for line in _skeleton_report(result.skeleton, args):
        say(line)
    say(f"session -> {result.session_path}")
    if not args.quiet:
        out = open_volume(result.output)
        print(f"straightened {args.input} -> {result.output}: shape {_fmt_triple(out.shape)} (s x y x x), spacing "
              f"{_fmt_triple(out.spacing)} {out.unit_abbreviation}")
        print(f"done in {time.perf_counter() - t_all:.1f} s")
    _say_results([result], lambda *a: None)
    return exit_status([result])


def cmd_demo(args: argparse.Namespace) -> int:
    from .demo import run_demo

    return run_demo(Path(args.output), quiet=args.quiet, overwrite=args.overwrite, n_fish=args.fish, seed=args.seed)


# ------------------------------------------------------------------------------------------------------------------
# parser
# ------------------------------------------------------------------------------------------------------------------
def _add_input_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--series", type=_series, default=None,
                   help="DICOM: which series to read (SeriesInstanceUID, SeriesNumber or 0-based index)")
    p.add_argument("--input-format", default=None, help="force the input format instead of detecting it")
    p.add_argument("--input-channel", default=None, metavar="NAME|INDEX",
                   help="a scan with several channels (OME-Zarr c axis, multi-channel TIFF): use this one (its name "
                        "or 0-based index); the session records it")


def _add_output_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--spacing", type=_spacing3, default=None,
                   help="override the voxel spacing, axis0,axis1,axis2 (or one number); needed for BMP/PNG stacks")
    p.add_argument("--unit", default=None, help="override the length unit (um, mm, ...)")
    p.add_argument("--nan-value", type=_finite, default=None,
                   help="replace NaN in float data by this value (default: NaN is an error)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output once the new one is complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")


def _add_skeleton_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--head", type=_triple, default=None, metavar="A0,A1,A2",
                   help="the head, full-resolution voxels in array index order (default: suggested)")
    p.add_argument("--tail", type=_triple, default=None, metavar="A0,A1,A2",
                   help="the tail, full-resolution voxels (default: suggested)")
    p.add_argument("--chain", type=_triple, nargs=2, action="append", metavar=("START", "END"),
                   help="a specimen in pieces: the start and end of one part, repeated for every part from head to "
                   "tail (the first starts at the head, the last ends at the tail)")
    p.add_argument("--no-twist", action="store_true",
                   help="do not estimate the twist (frames by parallel transport)")
    p.add_argument("--dorsal", type=_triple, action="append", default=None, metavar="A0,A1,A2",
                   help="a point on the specimen's dorsal side (full-resolution voxels), repeated for several: the "
                   "twist turns the cross-section's up (v) towards each and changes evenly between them, instead of "
                   "being estimated")
    p.add_argument("--dorsal-direction", type=_triple, default=None, metavar="D0,D1,D2",
                   help="a direction (axis0,axis1,axis2) that the cross-section's up (v) follows wherever the curve "
                   "crosses it, instead of the estimate (for a vessel: the patient's anterior)")
    d = _skeleton_default
    p.add_argument("--levels", type=_whole(2, 10000), default=None,
                   help=f"level sets of the harmonic field, 2-10000 (default {d('n_levels')})")
    p.add_argument("--smoothing-iterations", type=_whole(0, 100000), default=None,
                   help=f"curve smoothing iterations, 0-100000 (default {d('smoothing_iterations')})")
    p.add_argument("--cage-radius", type=_positive, default=None,
                   help="half size (voxels) of the box whose centre and corners the keyframes must reproduce within "
                   f"--tolerance (default {d('cage_radius')}): larger, more keyframes")
    p.add_argument("--tolerance", type=_positive, default=None,
                   help="how far (voxels) the keyframed box may stray from the dense curve's (default "
                   f"{d('tolerance')}): larger, fewer keyframes")
    p.add_argument("--snap-tolerance", type=_non_negative, default=None,
                   help="ends outside the mask move onto it when within this many voxels (default "
                   f"{d('snap_tolerance')})")
    p.add_argument("--cage", type=_cage_pair, default=None, metavar="RX,RY",
                   help="cage half extents along u and v for every keyframe, in the scan's unit (default: fitted "
                   "per keyframe and per side to the specimen's sections)")
    p.add_argument("--context", type=_non_negative, default=None, metavar="MM",
                   help="widen the straight volume by this much (the scan's unit) on every side of the fitted cages "
                   "and at both ends, to keep what surrounds the specimen; given up where a bend would fold the "
                   "cage, and reported (default 0)")
    p.add_argument("--cage-margin", type=_non_negative, default=None, metavar="M",
                   help=f"relative margin of the fitted cages (default {d('cage_margin')}: "
                   f"{100 * d('cage_margin'):.0f} %%; 2 voxels are added besides)")


def _skeleton_default(name: str) -> Any:
    """The default of a skeleton option: the one in :class:`napari_unwind.pipeline.SkeletonOptions`."""
    from .pipeline import SkeletonOptions

    return SkeletonOptions.__dataclass_fields__[name].default


def _cage_pair(text: str) -> tuple[float, float]:
    """``RX,RY`` (or one number for both): two positive finite numbers."""
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) == 1:
        values = values * 2
    if len(values) != 2 or not all(math.isfinite(v) and v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected two positive numbers RX,RY (half extents), got {text!r}")
    return (values[0], values[1])


def _add_max_output(p: argparse.ArgumentParser) -> None:
    p.add_argument("--max-output", type=parse_size, default=argparse.SUPPRESS, metavar="SIZE",
                   help="refuse to write an output larger than SIZE (before starting): e.g. 500G, 2T, 1.5GiB, "
                   "800MB or bytes (K M G T: powers of 1024, KB MB GB TB: of 1000); none: no limit (default: "
                   "napari_unwind.warp.DEFAULT_MAX_OUTPUT)")


#: One number or comma-separated numbers whose first is negative: "-3", "-3,10,10", "-1.5e2,0,.5".
_NEGATIVE_NUMBERS = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?(,[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)*$")


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose mistakes are one line and exit status 1, like every other error of ``unwind``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("epilog", EPILOG)
        super().__init__(*args, **kwargs)
        # a value such as -3,10,10 (--head -3,10,10, --at -1.5,2,2) is a value, not an unknown option: argparse's
        # own pattern knows only single numbers (-3, -.5); no option of unwind looks like a number
        self._negative_number_matcher = _NEGATIVE_NUMBERS

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(1, f"unwind: error: {' '.join(message.split())}; see {self.prog} --help\n")

    def parse_known_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                         namespace: argparse.Namespace | None = None) -> tuple[argparse.Namespace, list[str]]:
        """As argparse's, with ``--token VALUE`` read as ``--token=VALUE``: a token may begin with "-"."""
        args = sys.argv[1:] if args is None else list(args)
        if any(a in DASH_VALUE_OPTIONS for a in args):
            args = join_dash_values(args, option_strings(self))
        return super().parse_known_args(args, namespace)


def build_parser() -> argparse.ArgumentParser:
    from . import __version__
    from ._cli_remote import _add_token_options, add_remote_commands

    parser = _Parser(
        prog="unwind",
        description="Straighten bent and twisted specimens in 3D scans (napari-unwind).",
    )
    parser.add_argument("--version", action="version", version=f"napari-unwind {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser("info", help="print shape, dtype, spacing, pyramid levels and size on disk")
    p.add_argument("path", help="a scan in any supported format")
    _add_input_options(p)
    p.set_defaults(func=cmd_info)

    p = sub.add_parser("import", help="convert a scan to the working format: a chunked OME-Zarr pyramid")
    p.add_argument("input", help="a scan in any supported format")
    p.add_argument("output", help="the OME-Zarr folder to create (*.zarr)")
    p.add_argument("--chunks", type=_chunks, default=None, help="chunk shape (default 128)")
    p.add_argument("--max-side", type=_whole(1), default=256, help="halve until every side is <= this (default 256)")
    p.add_argument("--labels", action="store_true", help="the input holds labels: downsample by nearest")
    _add_input_options(p)
    _add_output_options(p)
    p.set_defaults(func=cmd_import)

    p = sub.add_parser("convert", help="write a scan in another format (chosen by the output's suffix)")
    p.add_argument("input", help="a scan in any supported format")
    p.add_argument("output", help="output path: .zarr .tif .nrrd .nhdr .nii(.gz) .dat .dicom, or name_{:04d}.png")
    p.add_argument("--format", default=None, help="force the output format instead of the suffix's")
    p.add_argument("--level", type=_whole(0), default=None,
                   help="write this pyramid level instead of full resolution")
    p.add_argument("--chunks", type=_chunks, default=None, help="OME-Zarr chunk shape")
    _add_input_options(p)
    _add_output_options(p)
    p.set_defaults(func=cmd_convert)

    p = sub.add_parser("segment", help="split a scan into its most important bright objects (join tree)")
    p.add_argument("input", help="a scan in any supported format (an imported OME-Zarr pyramid is fastest)")
    p.add_argument("-o", "--output", required=True, help="the label volume to write (*.zarr, working resolution)")
    p.add_argument("--features", type=_whole(1, 100), default=5,
                   help="number of features to keep, 1-100 (default 5)")
    p.add_argument("--level", type=_whole(0), default=None,
                   help="pyramid level to work on (default: the finest with every side <= 256)")
    p.add_argument("--smooth", type=_non_negative, default=1.0,
                   help="Gaussian sigma in working voxels (default 1; 0 none)")
    p.add_argument("--specimens", action="store_true",
                   help="list only the specimen-like features: elongated, inside the scan, not containers (a tube "
                        "or dish that touches the border or encloses others); with -q, print their ids alone")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output once the new one is complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    _add_input_options(p)
    p.set_defaults(func=cmd_segment)

    p = sub.add_parser("select", help="turn features picked by points or ids into a specimen mask")
    p.add_argument("labels", help="the label volume written by unwind segment")
    p.add_argument("--at", type=_triple, action="append", help="a point inside a feature, A0,A1,A2 in full-resolution "
                   "voxels (repeatable)")
    p.add_argument("--id", type=_whole(0), action="append", help="a feature id (repeatable)")
    p.add_argument("-o", "--output", required=True, help="the mask to write (any format; .zarr for large scans)")
    p.add_argument("--full-resolution", metavar="INPUT", default=None,
                   help="refine the mask at full resolution on this scan, chunk by chunk")
    p.add_argument("--isovalue", type=_finite, default=None,
                   help="full-resolution threshold (default: halfway between the medium and the body of the "
                   "features the mask covers, read from the scan)")
    p.add_argument("--fill-holes", action="store_true", help="fill cavities of the mask")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output once the new one is complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    _add_input_options(p)
    p.set_defaults(func=cmd_select)

    p = sub.add_parser("skeleton", help="estimate the deformation of a specimen mask: a session file")
    p.add_argument("mask", help="the specimen's mask (nonzero = inside), any format, e.g. from unwind select")
    p.add_argument("-o", "--output", required=True, help="the session file to write (*.unwind.json)")
    p.add_argument("--mask-label", type=_whole(1), default=None, metavar="N",
                   help="the mask is a label map: its voxels of label N are the specimen (default: every non-zero "
                   "voxel; a map of several labels is then named in a warning)")
    _add_skeleton_options(p)
    p.add_argument("--volume", metavar="SCAN", default=None,
                   help="the scan the mask belongs to (same shape): the session's source, the one unwind "
                   "straighten will straighten; also guides the twist and the head/tail choice")
    p.add_argument("--overwrite", action="store_true", help="replace an existing session file")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    _add_input_options(p)
    p.set_defaults(func=cmd_skeleton)

    p = sub.add_parser("run", help="the whole pipeline: segment, select, skeleton, straighten",
                       epilog=RUN_EPILOG)
    p.add_argument("input", help="the scan, any supported format")
    p.add_argument("-o", "--output", required=True, help="the straight volume to write; the suffix chooses the format "
                   "(with --all: a folder)")
    p.add_argument("--all", action="store_true",
                   help="straighten every specimen (elongated, inside the scan, not a container such as the tube) "
                   "with no click: -o OUTDIR gets specimen-ID.zarr, specimen-ID.unwind.json and specimens.csv "
                   "(length, keyframes, min Jacobian, tilt, coverage, status and reason; every candidate feature has "
                   "a row, rejected ones too); a specimen that fails is reported with its reason and the others go on")
    p.add_argument("--mask", default=None, help="the specimen's mask (same shape as INPUT) instead of segmenting")
    p.add_argument("--mask-label", type=_whole(1), default=None, metavar="N",
                   help="the mask is a label map: its voxels of label N are the specimen (default: every non-zero "
                   "voxel; a map of several labels is then named in a warning)")
    p.add_argument("--select", type=_triple, action="append", metavar="A0,A1,A2",
                   help="a point inside the specimen, full-resolution voxels (repeatable: several features)")
    p.add_argument("--features", type=_whole(1, 100), default=None,
                   help="features the segmentation keeps, 1-100 (default 5; with --all every feature above the noise "
                   "level, at most 100)")
    p.add_argument("--level", type=_whole(0), default=None,
                   help="pyramid level to segment (default: every side <= 256)")
    p.add_argument("--isovalue", type=_finite, default=None,
                   help="full-resolution threshold of the mask (default: halfway between the medium and the body of "
                   "the features it covers, read from the scan; the dimmest of them, an enclosed one too with "
                   "--fill-holes)")
    p.add_argument("--fill-holes", action="store_true", help="fill cavities of the mask")
    p.add_argument("--session", default=None,
                   help="the session file to write (default: OUTPUT's name + .unwind.json beside OUTPUT)")
    _add_skeleton_options(p)
    p.add_argument("--order", type=int, choices=(0, 1, 3), default=None,
                   help="interpolation: 0 nearest (labels), 1 linear (default), 3 cubic")
    p.add_argument("--pad", type=_whole(0), default=None, help="extra slices at both ends (default 0)")
    p.add_argument("--spacing", type=_positive, default=None, help="output voxel size (default: finest scan spacing)")
    p.add_argument("--chunks", type=_chunks, default=None, help="output chunk shape (default 64 x cross-section)")
    _add_max_output(p)
    p.add_argument("--allow-folds", action="store_true", help="export even where the deformation folds")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs once the new ones are complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    p.add_argument("--server", default=None, metavar="HOST:PORT",
                   help="run the whole pipeline as a job on this napari-unwind server instead of in this process")
    _add_token_options(p)
    _add_input_options(p)
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("straighten", help="export the straight volume of a session's deformation")
    p.add_argument("input", nargs="+",
                   help="the scan the session was made on (any supported format); more images of its grid (other "
                        "channels, stains) or a scan with a channel axis give one multi-channel output (.zarr with a "
                        "c axis, or an ImageJ hyperstack .tif), straightened in one pass")
    p.add_argument("--session", required=True, help="the session file (*.unwind.json) holding the deformation")
    p.add_argument("-o", "--output", required=True, help="output path; the suffix chooses the format")
    p.add_argument("--channel-names", default=None, metavar="A,B,...",
                   help="names of the channels, in order (default: the file's channel names, else the file names)")
    p.add_argument("--order", type=int, choices=(0, 1, 3), default=1,
                   help="interpolation: 0 nearest (labels), 1 linear (default), 3 cubic")
    p.add_argument("--pad", type=_whole(0), default=0, help="extra slices at both ends (default 0)")
    p.add_argument("--spacing", type=_positive, default=None, help="output voxel size (default: finest scan spacing)")
    p.add_argument("--chunks", type=_chunks, default=None, help="output chunk shape (default 64 x cross-section)")
    _add_max_output(p)
    p.add_argument("--scheduler", type=_address, default=None,
                   help="dask.distributed scheduler address (tcp://host:8786) to run on a cluster")
    p.add_argument("--allow-folds", action="store_true", help="export even where the deformation folds")
    p.add_argument("--no-verify", action="store_true", help="skip checking the scan against the session's checksum")
    p.add_argument("--same-grid", action="store_true",
                   help="INPUT is another image of the session's scan grid (a channel, a stain): check its shape, "
                        "spacing and origin instead of the scan's checksum; the output's session records it")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output once the new one is complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    _add_input_options(p)
    p.set_defaults(func=cmd_straighten)

    p = sub.add_parser("measure", help="measure the specimen along the session's centreline: a CSV or Parquet "
                                       "profile, and its plot")
    p.add_argument("--session", required=True, help="the session file (*.unwind.json) holding the deformation")
    p.add_argument("--mask", default=None,
                   help="the specimen mask on the scan's grid (default: the session's mask file, when it has one)")
    p.add_argument("--mask-label", type=_whole(1), default=None, metavar="N",
                   help="the mask is a label map: its voxels of label N are the specimen (default: the session's label "
                   "with its mask file; every non-zero voxel of a mask given here)")
    p.add_argument("--labels", default=None, help="a label image on the scan's grid: an area column per label")
    p.add_argument("--channel", action="append", type=_channel_arg, default=[], metavar="[NAME=]PATH",
                   help="an intensity image on the scan's grid (repeatable): mean, std, min, max per station")
    p.add_argument("--spacing", type=_positive, default=None,
                   help="station spacing and section pixel size (default: finest scan spacing)")
    p.add_argument("-o", "--output", required=True,
                   help="the profile: .csv, or .parquet (pip install napari-unwind[tables]); units with each column")
    p.add_argument("--plot", default=None, metavar="PNG",
                   help="also plot the profiles against s to this .png (pip install napari-unwind[plot])")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output once the new one is complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    p.set_defaults(func=cmd_measure)

    p = sub.add_parser("average", help="the average straight specimen of a batch: mean, median, std, residuals")
    p.add_argument("inputs", nargs="+", help="straight volumes, or folders of them (unwind straighten's outputs)")
    p.add_argument("-o", "--output", required=True,
                   help="the mean (suffix = format); the median, std and residuals.csv are written beside it")
    p.add_argument("--stations", type=_whole(2), default=None, help="stations along s (default: the median length)")
    p.add_argument("--scale", choices=("length", "none"), default="length",
                   help="scale each cross-section with its length (default, compares shape) or keep its size")
    p.add_argument("--normalise", choices=("robust", "none"), default="robust",
                   help="per specimen: median -> 0, 99th percentile -> 1 (default), or keep the grey values")
    p.add_argument("--max-roll", type=float, default=90.0, help="largest roll searched each way (degrees)")
    p.add_argument("--landmarks", default=None, metavar="FILE.csv",
                   help="landmarks along s: per row a specimen's name or path, then its K positions (arc length "
                        "from the head, the specimens' unit); each lands on the batch's mean position")
    p.add_argument("--scheduler", type=_address, default=None,
                   help="dask.distributed scheduler address (tcp://host:8786) to run on a cluster")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs once the new ones are complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    p.set_defaults(func=cmd_average)

    p = sub.add_parser("bend", help="put a straight volume back into the pose of the session's scan")
    p.add_argument("input", help="a straight volume (e.g. from unwind straighten, or stained and edited)")
    p.add_argument("--session", required=True, help="the session file (*.unwind.json) holding the deformation")
    p.add_argument("-o", "--output", required=True, help="output path; the suffix chooses the format")
    p.add_argument("--order", type=int, choices=(0, 1, 3), default=1, help="interpolation order (default 1)")
    p.add_argument("--chunks", type=_chunks, default=None, help="output chunk shape")
    _add_max_output(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output once the new one is complete")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    p.set_defaults(func=cmd_bend, no_verify=True)
    _add_input_options(p)

    p = sub.add_parser("map-points", help="carry points between the scan and the straight volume")
    p.add_argument("points", nargs="?", help="CSV of points in full-resolution voxels, array index order: napari's "
                   "Points CSV (index,axis-0,axis-1,axis-2) or 3 columns with or without a header; ',', ';' or tab "
                   "separated, '.' as the decimal mark")
    p.add_argument("--at", type=_triple, action="append", help="one point A0,A1,A2 (repeatable; instead of a file)")
    p.add_argument("--session", required=True, help="the session file (*.unwind.json) holding the deformation")
    p.add_argument("--to", choices=("straight", "scan"), default="straight",
                   help="straight: scan voxels -> straight voxels (default); scan: the other way")
    p.add_argument("--spacing", type=_positive, default=None,
                   help="straight volume spacing (default: finest scan)")
    p.add_argument("-o", "--output", default=None, help="CSV to write (default: print)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("-q", "--quiet", action="store_true", help="no report")
    p.set_defaults(func=cmd_map_points, no_verify=True)

    p = sub.add_parser("demo", help="run the pipeline on the bundled synthetic tank of fish")
    p.add_argument("-o", "--output", default="unwind-demo", help="folder for the demo's files (default unwind-demo)")
    p.add_argument("--fish", type=_whole(1), default=3, help="number of fish in the tank (default 3)")
    p.add_argument("--seed", type=_whole(0), default=0, help="random seed of the phantom (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace outputs of an earlier demo run")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or report")
    p.set_defaults(func=cmd_demo)

    # the remote faces: serve, submit, jobs (and run --server above)
    add_remote_commands(sub)
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread: handled like Ctrl-C (outputs being written are removed)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


_SIGNALS = {signal.SIGTERM: "terminated (SIGTERM)"}
if hasattr(signal, "SIGHUP"):
    _SIGNALS[signal.SIGHUP] = "hung up (SIGHUP)"


class _Interrupt:
    """The interrupt of this run: the first signal raises it; later ones are ignored, so that they cannot
    interrupt the removal of the outputs being written (the run still ends with the first one's status)."""

    raised: KeyboardInterrupt | None = None  # raised and not lost (yet)
    lost: KeyboardInterrupt | None = None  # raised where no exception can pass: to be raised again
    signum: int | None = None
    in_hook = False
    timer: threading.Timer | None = None


def _on_signal(signum: int, frame: Any) -> None:
    if _Interrupt.in_hook:  # not here, where it would be lost again: a moment later
        _raise_again_soon()
        return
    if _Interrupt.lost is not None:
        exc, _Interrupt.lost = _Interrupt.lost, None
    elif _Interrupt.raised is not None:
        return
    else:
        exc = KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)
        _Interrupt.signum = signum
    _Interrupt.raised = exc
    raise exc


def _raise_again_soon() -> None:
    import _thread

    timer = threading.Timer(0.001, _thread.interrupt_main, (_Interrupt.signum,))  # runs _on_signal again
    timer.daemon = True
    timer.start()
    _Interrupt.timer = timer


def _unraisable(args: Any, *, hook: Callable[[Any], None]) -> None:
    """sys.unraisablehook: the interrupt raised where no exception can pass (a callback of compiled code through
    ctypes or Cython, a ``__del__``) is raised again a moment later instead of being lost (a SIGTERM that landed
    there once let the run go on and end with 0); :func:`main` raises it at the latest when the command returns."""
    if args.exc_value is not None and args.exc_value is _Interrupt.raised:
        _Interrupt.in_hook = True
        try:
            _Interrupt.lost, _Interrupt.raised = _Interrupt.raised, None
            _raise_again_soon()
        finally:
            _Interrupt.in_hook = False
        return
    hook(args)


def _install_signal_handlers() -> Callable[..., None]:
    """Handle SIGINT, SIGTERM and SIGHUP with :func:`_on_signal` (main thread only); returns the undo.

    A signal the process inherited ignored stays ignored (``nohup``; a background job of a non-interactive shell
    ignores SIGINT). fTetWild, which resets SIGINT's handler behind Python's back, runs in a child process
    (:func:`napari_unwind._compat.tetrahedralize`).
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda ignore=False: None
    _Interrupt.raised = _Interrupt.lost = _Interrupt.signum = None
    previous = {}
    for s in (signal.SIGINT, *_SIGNALS):
        if signal.getsignal(s) is not signal.SIG_IGN:
            previous[s] = signal.signal(s, _on_signal)
    hook = sys.unraisablehook
    sys.unraisablehook = lambda args: _unraisable(args, hook=hook)

    def undo(ignore: bool = False) -> None:
        """Put the handlers back; ``ignore``: ignore these signals from now on instead. That is for the command
        itself (argv from sys.argv) once interrupted: it is exiting, and a further signal must not turn its
        status into -2 while the interpreter shuts down (which resets Python's handlers to SIG_DFL first, then
        can take seconds to join the threads of an abandoned computation)."""
        if _Interrupt.timer is not None:
            _Interrupt.timer.cancel()
        sys.unraisablehook = hook
        for s, handler in previous.items():
            signal.signal(s, signal.SIG_IGN if ignore else handler)

    return undo


def _show_warning(message: Any, category: Any, filename: str, lineno: int, file: Any = None,
                  line: Any = None) -> None:
    """A library's warning as the command line says it: one ``unwind: warning: ...`` line."""
    print(f"unwind: warning: {_one_line(str(message))}", file=sys.stderr)


def _one_line(message: str) -> str:
    """A message on one line (its lines joined), as every error of the command line is."""
    return " ".join(line.strip() for line in message.splitlines() if line.strip())


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``unwind`` command. Returns the exit status (see the module's docstring)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, --version (0), a wrong option (1, one line printed)
        return exc.code if isinstance(exc.code, int) else 1
    func: Callable[[argparse.Namespace], int] = args.func
    restore_signals = _install_signal_handlers()
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            source_date_epoch()  # before any import reads it (numpy's f2py fails on a bad one with a traceback)
            status = func(args)
            if _Interrupt.lost is not None:  # a signal that landed where it was lost, and never raised again
                raise _Interrupt.lost
        sys.stdout.flush()  # a closed pipe shows here, not at exit
        return status
    except BrokenPipeError:
        # the reader of our output went away (unwind info X | head): stop quietly, as cat or grep do
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):  # stdout is no real file (captured)
            pass
        return 0
    except (UnwindError, OSError) as exc:
        print(f"unwind: error: {_one_line(str(exc))}", file=sys.stderr)
        return 1
    except MemoryError as exc:
        print(f"unwind: error: out of memory{': ' + _one_line(str(exc)) if str(exc) else ''}; make the output smaller "
              "(--spacing, --pad, a pyramid level) or use a machine with more memory", file=sys.stderr)
        return 1
    except KeyboardInterrupt as exc:
        # work abandoned on purpose: complaints at exit about zarr's coroutines left pending are not news
        logging.getLogger("asyncio").setLevel(logging.CRITICAL)
        warnings.filterwarnings("ignore", message="coroutine .* was never awaited", category=RuntimeWarning)
        if isinstance(exc, Terminated):
            print(f"unwind: {_SIGNALS[exc.signum]}; no partial output was left behind", file=sys.stderr)
            return 128 + exc.signum
        print("unwind: interrupted; no partial output was left behind", file=sys.stderr)
        return 130
    finally:
        if _Interrupt.signum is not None:
            # the interrupted work has unwound here (its generators closed, each output's own removal run): what a
            # write still in flight left or made again is removed before the command says it is gone
            import gc

            from .io._atomic import sweep

            gc.collect()  # generators held in reference cycles close now, running their own removal first
            sweep()
        restore_signals(ignore=argv is None and _Interrupt.signum is not None)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
