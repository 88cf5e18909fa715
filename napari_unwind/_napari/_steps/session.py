"""Step 7, Session: save and open a session (:mod:`napari_unwind.session`) at any step."""

from __future__ import annotations

import os
from collections.abc import Generator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from qtpy.QtWidgets import QFileDialog, QHBoxLayout, QLabel, QPushButton, QVBoxLayout

from ...errors import InvalidInputError, UnwindError
from ...io import Volume, open_volume
from ...progress import Progress
from .._reader import contrast_limits
from .._workers import Job
from ._base import Step


def _with_geometry(volume: Volume, spacing: Any, origin: Any) -> Volume:
    """``volume`` with another spacing and origin (a session's), its pyramid levels scaled alike."""
    sp0, sp = np.asarray(volume.spacing, dtype=float), np.asarray(spacing, dtype=float)
    ratio = sp / sp0
    level_spacings = tuple(tuple(float(v) for v in np.asarray(ls) * ratio) for ls in volume.level_spacings)
    level_origins = tuple(tuple(float(v) for v in np.asarray(origin, dtype=float) + (np.asarray(ls) - sp) / 2)
                          for ls in level_spacings)
    return replace(volume, spacing=tuple(float(v) for v in sp), origin=tuple(float(v) for v in origin),
                   level_spacings=level_spacings, level_origins=level_origins)


class SessionStep(Step):
    """Save the workflow's state as a session, or open one: its scan, ends, deformation and selection."""

    def __init__(self, dock: Any) -> None:
        super().__init__(dock)
        lay = QVBoxLayout(self)
        row = QHBoxLayout()
        save = QPushButton("Save session...")
        save.clicked.connect(self._save_dialog)
        load = QPushButton("Open session...")
        load.clicked.connect(self._load_dialog)
        row.addWidget(save)
        row.addWidget(load)
        lay.addLayout(row)
        self.session_info = QLabel("A session (*.unwind.json) keeps the scan, the selection, the ends and the "
                                   "deformation; save it at any step.")
        self.session_info.setWordWrap(True)
        lay.addWidget(self.session_info)
        lay.addStretch(1)

    def _save_dialog(self) -> None:
        path, _ = QFileDialog.getSaveFileName(self, "Save the session", "", "Sessions (*.unwind.json)")
        if path:
            self.save_session(path)

    def _load_dialog(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "Open a session", "", "Sessions (*.unwind.json)")
        if path:
            self.load_session(path)

    def save_session(self, path: str | os.PathLike) -> Job | None:
        """Save the current state as a session (the scan's checksum is computed once, in a worker).

        A session records the scan's file. A scan that has none (File > Open Sample, a layer made in napari) is
        written first, beside the session, as ``<name>.scan.ome.zarr``, and the session records that file: it
        opens again from the dock and from File > Open. The dock then works on that file.

        A mask chosen as the selection is recorded by its file when that file holds the chosen voxels (a mask file
        opened in step 2, a Labels layer read from a file and not painted since); otherwise the chosen voxels are
        written beside the session as ``<name>.mask.ome.zarr`` and the session records that.
        """
        from ...session import SESSION_SUFFIX, SourceInfo, save_session

        dock, workflow = self.dock, self.workflow
        volume = dock.volume
        path = Path(path).expanduser()
        try:
            if volume is None:
                raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
            workflow.session(SourceInfo(path=volume.source or "scan", shape=volume.shape, dtype=volume.dtype.name,
                                        spacing=volume.spacing))  # checks selection and ends before hashing
            scan_file = None
            if not volume.source or not Path(volume.source).exists():
                stem = path.name[:-len(SESSION_SUFFIX)] if path.name.endswith(SESSION_SUFFIX) else path.stem
                scan_file = path.with_name(f"{stem}.scan.ome.zarr")
                if scan_file.exists():
                    raise InvalidInputError(
                        f"the scan {dock.scan_layer.name!r} has no file, and the session would write it to "
                        f"{scan_file}, which exists: choose another session name, or move that file away")
        except UnwindError as exc:
            self._fail(exc)
            return None
        known = workflow.source_info if scan_file is None else None
        selection = workflow.selection
        stem = path.name[:-len(SESSION_SUFFIX)] if path.name.endswith(SESSION_SUFFIX) else path.stem
        mask_target = path.with_name(f"{stem}.mask.ome.zarr")

        def write_mask() -> Generator[Progress, None, Path | None]:
            """The chosen mask's file: None when the recorded one holds the chosen voxels, else written beside."""
            if selection.mask is None:
                return None
            if selection.source is not None and Path(selection.source).exists():
                try:
                    recorded = np.asarray(open_volume(selection.source).data)
                    if recorded.shape == selection.mask.shape and np.array_equal(
                            recorded == selection.label if selection.label else recorded != 0, selection.mask):
                        return None
                except UnwindError:
                    pass  # not readable as a mask: write the chosen voxels instead
            if mask_target.exists():
                raise InvalidInputError(f"the mask has no file holding its voxels, and the session would write it "
                                        f"to {mask_target}, which exists: choose another session name, or move "
                                        "that file away")
            from ...io import write_volume_iter

            return (yield from write_volume_iter(np.asarray(selection.mask, dtype=np.uint8), mask_target,
                                                 spacing=volume.spacing, unit=volume.unit, origin=volume.origin,
                                                 labels=True))

        def make() -> Generator[Progress, None, Any]:
            mask_file = yield from write_mask()
            if known is not None:
                return known, volume, mask_file
            scan = volume
            if scan_file is not None:
                from ...io import write_volume_iter

                written = yield from write_volume_iter(volume, scan_file)
                scan = _with_geometry(open_volume(written), volume.spacing, volume.origin)
            yield Progress("checksum", 0, 1, scan.source)
            info = SourceInfo.from_path(scan.source, volume=scan)  # reads every byte once
            yield Progress("checksum", 1, 1)
            return info, scan, mask_file

        def done(result: Any) -> None:
            source, scan, mask_file = result
            workflow.source_info = source
            if mask_file is not None and workflow.selection is selection:
                workflow.mask_written(mask_file)
            if scan is not volume:
                workflow.volume = scan  # the dock now works on the file the session records (same voxels)
                meta = dict(dock.scan_layer.metadata or {})
                meta["napari_unwind"] = {**meta.get("napari_unwind", {}), "source": scan.source,
                                         "format": scan.format}
                dock.scan_layer.metadata = meta
            written = save_session(workflow.session(source), path)
            saved_scan = f" with its scan {scan.source}" if scan is not volume else ""
            if mask_file is not None:
                saved_scan += f"{' and' if saved_scan else ' with'} its mask {mask_file}"
            self.session_info.setText(f"saved: {written}{saved_scan}")
            self._say(f"session saved to {written}{saved_scan}")

        return dock._start(make, "saving the session", done)

    def load_session(self, path: str | os.PathLike) -> Job | None:
        """Open a session: its scan (a layer), the ends, the deformation, and the selection (the join tree is
        rebuilt in a worker, then the recorded features are selected; or the recorded mask file is opened)."""
        from ...session import load_session

        try:
            session = load_session(path)
        except (UnwindError, FileNotFoundError) as exc:
            self._fail(exc)
            return None
        src = session.source
        dock = self.dock

        def make() -> Generator[Progress, None, Volume]:
            yield Progress("open", 0, 1, src.path)
            if not Path(src.path).exists():
                raise InvalidInputError(f"the session's scan is missing: expected at {src.path}; put it back or "
                                        "correct \"source\" -> \"path\" in the session file")
            from ...session import open_source

            volume = open_source(src)
            if volume.shape != tuple(src.shape):
                raise InvalidInputError(f"the scan at {src.path} holds {volume.shape} voxels, the session's scan "
                                        f"{tuple(src.shape)}: it is not the scan the session was made from")
            yield Progress("open", 1, 1)
            origin = session.deformation.origin if session.deformation is not None else volume.origin
            return _with_geometry(volume, src.spacing, origin), contrast_limits(volume.levels)

        def done(value: tuple) -> None:
            from .._layers import image_layer

            volume, clim = value
            layer = dock._add_layer(image_layer(volume, contrast_limits=clim))
            self.workflow.volume = None  # a fresh start, even on the same scan
            dock._set_scan(volume, layer)
            self.workflow.source_info = src if src.checksum else None
            self.workflow.twist = session.twist
            if session.endpoints is not None:
                dock.ends_step.show_session_ends(session.endpoints)
            if session.deformation is not None:
                self.workflow.edit.set_deformation(session.deformation)
            seg = session.segmentation
            if seg is not None and seg.mask is not None:
                dock.job = None
                dock.segment_step.open_mask(seg.mask, label=seg.mask_label)
            elif seg is not None and seg.k is not None and (seg.selected or seg.seeds):
                dock.job = None
                dock.segment_step.resume(seg)
            self.session_info.setText(f"opened: {Path(path).absolute()}")

        return dock._start(make, "opening the session", done)
