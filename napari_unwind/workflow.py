"""The interactive workflow as a Qt-free model: its state, its steps, and one backend interface.

The Unwind dock (:mod:`napari_unwind._napari._widget`) is a view over :class:`Workflow`, as the 2D editor is over
:class:`~napari_unwind.editing.EditModel` and as napari-animation keeps its ``Animation`` apart from its widget.
It imports neither napari nor Qt: tests and scripts drive it the same way (``tests/test_workflow_model.py``).

State
    ``volume`` (the scan), ``tree`` and ``features`` (the join tree and its simplification), the selection
    (``selected`` feature ids with their ``seeds``, or a chosen ``mask``), ``ends``, ``specimen`` (the last
    skeleton's :class:`~napari_unwind.pipeline.SpecimenResult`), the deformation (``edit``, an EditModel, so the
    Refine step's edits and undo act on it), ``options`` (:class:`~napari_unwind.pipeline.PipelineOptions`: the
    export settings among them) and the session (:meth:`Workflow.session`).
Steps
    Each long step returns a :class:`Task`: ``make()`` builds a progress generator (run it off the UI thread) and
    ``apply(result)`` puts its result into the state (run it on the UI thread, which the events then reach).
    :func:`napari_unwind.progress.run` runs a task in a script: ``wf.apply(task, run(task.make()))``.
Backends
    Where the work runs is the :class:`Backend`'s business: :class:`LocalBackend` (the core's pipeline on this
    computer) or :class:`ServerBackend` (the same steps as jobs of an ``unwind serve``, through the client). Every
    step is written once against the interface; no step asks which backend it has.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from psygnal import Signal

from .editing import EditModel
from .errors import InvalidInputError
from .pipeline import ExportOptions, PipelineOptions, SkeletonOptions, as_label_map, specimen_mask
from .progress import Progress

__all__ = ["Backend", "LocalBackend", "ServerBackend", "Selection", "Task", "Workflow", "mask_labels", "read_mask"]

#: The skeleton step run by name in a child process (its module imports the solver while the child waits).
SKELETON = "napari_unwind._steps:skeleton"

Runner = Callable[[str, tuple, dict], Generator[Progress, None, Any]]


@dataclass(frozen=True)
class Task:
    """A long step: ``make()`` gives its progress generator (off the UI thread), ``apply(result)`` takes the
    result into the workflow (on the UI thread)."""

    label: str
    make: Callable[[], Generator[Progress, None, Any]]
    apply: Callable[[Any], Any]


def mask_labels(mask: Any) -> tuple[np.ndarray, str | None]:
    """The voxels of a mask (a Volume or an array) as labels for a Labels layer: integers as they are (a float map
    of whole values too, as int64), anything else as 1 where it is the specimen
    (:func:`~napari_unwind.pipeline.specimen_mask`: non-zero, or a map of fractional values thresholded), as uint8.
    Returns ``(labels, note)``: the note says how a map of fractional values was thresholded (None otherwise)."""
    data, note = np.asarray(getattr(mask, "data", mask)), None
    if not (np.issubdtype(data.dtype, np.integer) or data.dtype == np.bool_):
        labels = as_label_map(data)  # a label map saved as float: its labels; a map of fractional values thresholded
        if labels is not None:
            data = np.asarray(labels)
        else:
            kept, note = specimen_mask(data)
            data = np.asarray(kept) != 0
    return (data.astype(np.uint8) if data.dtype == np.bool_ else data), note


def read_mask(path: Any, scan: Any, *, session: str | None = None) -> tuple[np.ndarray, tuple[str, ...]]:
    """The voxels of the mask file at ``path`` as labels (:func:`mask_labels`) on the grid of the ``scan`` (a
    Volume): a mask of its shape voxel for voxel, or a box of its grid placed by the file's origin
    (:func:`~napari_unwind.io._grid.place_on_grid`). ``session`` names the session that recorded the file (its errors
    then say how to mend the session; the mask is then expected to be the one the session was made with).

    Returns ``(labels, notes)``: the notes (one line each) say what was done to read it as the scan's mask: a box
    placed by its origin, a map of fractional values thresholded. Empty when it was taken as it is."""
    from .io import open_volume
    from .io._grid import place_on_grid
    from .session import SourceChangedError, SourceMissingError

    path = Path(path)
    if not path.exists():
        mend = ('correct "segmentation" -> "mask" in the session file' if session else "choose the mask again")
        raise SourceMissingError(f"the mask {f'of {session}' if session else 'file'} is missing: expected at {path}; "
                                 f"put it back there, or {mend}")
    mask = open_volume(path)
    try:
        placed, placed_note = place_on_grid(mask, scan)
    except InvalidInputError as exc:
        if session:
            raise SourceChangedError(f"{exc} (the scan of {session}): it is not the mask the session was made "
                                     "with") from None
        raise
    labels, threshold_note = mask_labels(placed.data)
    return labels, tuple(n for n in (placed_note, threshold_note) if n)


@dataclass(frozen=True)
class Selection:
    """What the specimen is: features of a segmentation (``ids``, with the clicked ``seeds``), or a chosen
    ``mask`` (a boolean array on the scan's grid; ``key`` tells two masks apart without comparing voxels; ``source``
    is the mask's file and ``label`` its label that was chosen, as a session records them)."""

    features: Any = None
    ids: tuple[int, ...] = ()
    seeds: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    mask: Any = None
    key: Any = None
    options: Any = None  # SegmentOptions
    source: str | None = None
    label: int | None = None

    def full_mask(self, volume: Any) -> Any:
        """The selection at full resolution (a lazy dask bool array): the chosen mask, or the features refined by
        the pipeline's select_step with the segmentation options."""
        import dask.array as da

        if self.mask is not None:
            return da.asarray(self.mask).astype(bool)
        from .pipeline import SegmentOptions, select_step
        from .progress import run

        return run(select_step(volume, self.features, ids=list(self.ids),
                               options=self.options or SegmentOptions())).mask


@dataclass(frozen=True)
class Skeletonized:
    """A skeleton step's outcome, from either backend."""

    specimen: Any  # SpecimenResult (status, reason, figures, warnings)
    deformation: Any
    endpoints: Any = None
    where: str = ""  # "" on this computer, " (server host:port, session ...)" on a server
    twist: Any = None  # the session's TwistProfile (where the twist was estimated)


class Backend(Protocol):
    """Where the steps run. Each method returns a progress generator; ``label`` names the place in messages."""

    label: str

    def forget(self) -> None:
        """Drop what the backend keeps of the current scan (a new scan was chosen)."""

    def segment(self, volume: Any, *, name: str, level: int | None, smooth: float, k: int
                ) -> Generator[Progress, None, tuple[Any, Any]]:
        """The join tree: returns ``(tree, features)``: ``tree.simplify(k)`` gives Features, ``tree.n_maxima``
        its maxima (0: unknown); ``features`` the ``k`` features when the backend made them already, else None."""

    def suggest_ends(self, volume: Any, selection: Selection, *, name: str
                     ) -> Generator[Progress, None, list]:
        """Head and tail of the selection (full-resolution voxels)."""

    def skeleton(self, volume: Any, selection: Selection, ends: Any, *, name: str, options: SkeletonOptions
                 ) -> Generator[Progress, None, Skeletonized]:
        """The pipeline's skeleton step, judged."""

    def check_export(self, deformation: Any) -> None:
        """Raise InvalidInputError, before any work, when this backend cannot export ``deformation``."""

    def export(self, volume: Any, deformation: Any, target: Path, *, name: str, options: ExportOptions,
               folded: float | None, session: Any, overwrite: bool, channels: Sequence[Any] = ()
               ) -> Generator[Progress, None, tuple[Path, tuple[str, ...]]]:
        """Straighten and write ``target`` (with ``channels``, other images of the scan's grid, as one
        multi-channel image); returns (the written path, the warnings the fold rule let through)."""


def _in_this_process(fn: str, args: tuple, kwargs: dict) -> Generator[Progress, None, Any]:
    import importlib

    module, name = fn.split(":")
    return (yield from getattr(importlib.import_module(module), name)(*args, **kwargs))


class LocalBackend:
    """The core's pipeline on this computer. ``runner(fn, args, kwargs)`` runs the skeleton step (a
    ``"module:function"`` progress generator): in this process by default; the dock gives a child process (the
    solver holds the GIL for seconds)."""

    label = "this computer"

    def __init__(self, runner: Runner | None = None) -> None:
        self.runner = runner or _in_this_process

    def forget(self) -> None:
        pass

    def segment(self, volume: Any, *, name: str, level: int | None, smooth: float, k: int
                ) -> Generator[Progress, None, tuple[Any, Any]]:
        from .segmentation import join_tree_iter

        tree = yield from join_tree_iter(volume, level=level, smooth=smooth)
        return tree, None

    def suggest_ends(self, volume: Any, selection: Selection, *, name: str) -> Generator[Progress, None, list]:
        from .skeleton import suggest_endpoints

        mask = selection.full_mask(volume)
        yield Progress("mask", 0, 1, "full resolution")
        full = np.asarray(mask.compute())
        yield Progress("ends", 0, 1, "longest geodesic")
        ends = suggest_endpoints(full, spacing=volume.spacing, volume=volume.data)
        yield Progress("ends", 1, 1)
        return list(ends)

    def skeleton(self, volume: Any, selection: Selection, ends: Any, *, name: str, options: SkeletonOptions
                 ) -> Generator[Progress, None, Skeletonized]:
        mask = selection.full_mask(volume)
        specimen = yield from self.runner(SKELETON, (mask, ends), dict(
            spacing=volume.spacing, origin=volume.origin, unit=volume.unit, volume=volume.data, options=options))
        result = specimen.skeleton
        return Skeletonized(specimen, result.deformation, result.endpoints, twist=result.twist_profile())

    def check_export(self, deformation: Any) -> None:
        pass

    def export(self, volume: Any, deformation: Any, target: Path, *, name: str, options: ExportOptions,
               folded: float | None, session: Any, overwrite: bool, channels: Sequence[Any] = ()
               ) -> Generator[Progress, None, tuple[Path, tuple[str, ...]]]:
        from ._steps import export

        return (yield from export(volume, deformation, target, options=options, folded=folded, session=session,
                                  overwrite=overwrite, channels=channels))


class _ServerTree:
    """The server's segmentation, simplified there (the features' label volume downloaded)."""

    def __init__(self, server: Any, segmentation_id: str, n_maxima: int) -> None:
        self.server, self.segmentation_id, self.n_maxima = server, segmentation_id, n_maxima

    def simplify(self, k: int) -> Any:
        from ._remote import simplify

        return simplify(self.server, self.segmentation_id, int(k))


class ServerBackend:
    """The same steps as jobs of a server (``unwind serve``), through :class:`napari_unwind.client.Client`.

    The scan is uploaded once (or registered, when ``server_path`` names it under the server's data root), the
    selection's mask made there once per selection (a Select job of the server's segmentation, or the mask made
    here uploaded), and the skeleton's session kept there: an export straightens that session on the server, so
    a deformation edited here (another object) is refused with what to do.
    """

    def __init__(self, server: Any, *, server_path: str = "") -> None:
        self.server = server
        self.server_path = server_path
        self.label = f"server {server.address}"
        self._ids: dict[str, Any] = {}

    def forget(self) -> None:
        self._ids = {}

    def check_export(self, deformation: Any) -> None:
        known = self._ids.get("session")
        if known is None or known[1].to_dict() != deformation.to_dict():
            raise InvalidInputError("the server holds no session of this deformation (it was edited, or opened "
                                    "here): compute the skeleton on the server, or export on 'this computer'")

    def _volume_id(self, volume: Any, name: str) -> Generator[Progress, None, str]:
        from ._remote import register_iter, upload_iter

        if "volume_id" not in self._ids:
            path = self.server_path.strip()
            self._ids["volume_id"] = yield from (register_iter(self.server, path, volume, name=name) if path
                                                 else upload_iter(self.server, volume, name=name))
        return self._ids["volume_id"]

    def _mask_id(self, volume: Any, selection: Selection, volume_id: str) -> Generator[Progress, None, str]:
        from ._remote import mask_volume, select_iter, upload_iter

        seg = self._ids.get("segmentation")  # the features are the server's (forget() drops it otherwise)
        f = selection.features
        if selection.mask is not None:
            seg, key = None, ("mask", selection.key)
        elif seg is not None:
            key = (seg, f.k, tuple(selection.ids))
        else:
            key = (id(f), tuple(selection.ids))
        known = self._ids.get("mask")
        if known is not None and known[0] == key:
            return known[1]
        if seg is not None:
            mask_id = yield from select_iter(self.server, seg, key[2], key[1])
        else:
            local = selection.full_mask(volume)
            mask_id = yield from upload_iter(self.server, mask_volume(local, volume), labels=True, name="selection")
        self._ids["mask"] = (key, mask_id)
        return mask_id

    def segment(self, volume: Any, *, name: str, level: int | None, smooth: float, k: int
                ) -> Generator[Progress, None, tuple[Any, Any]]:
        from ._remote import segment_iter

        volume_id = yield from self._volume_id(volume, name)
        seg, maxima, features = yield from segment_iter(self.server, volume_id, features=k, level=level)
        self._ids["segmentation"] = seg
        self._ids.pop("mask", None)
        return _ServerTree(self.server, seg, maxima), features

    def suggest_ends(self, volume: Any, selection: Selection, *, name: str) -> Generator[Progress, None, list]:
        from ._remote import suggest_ends_iter

        volume_id = yield from self._volume_id(volume, name)
        mask_id = yield from self._mask_id(volume, selection, volume_id)
        return list((yield from suggest_ends_iter(self.server, volume_id, mask_id)))

    def skeleton(self, volume: Any, selection: Selection, ends: Any, *, name: str, options: SkeletonOptions
                 ) -> Generator[Progress, None, Skeletonized]:
        from ._remote import skeleton_iter

        volume_id = yield from self._volume_id(volume, name)
        mask_id = yield from self._mask_id(volume, selection, volume_id)
        session, session_id, specimen = yield from skeleton_iter(self.server, volume_id, mask_id, ends,
                                                                 options=options)
        self._ids["session"] = (session_id, session.deformation)
        return Skeletonized(specimen, session.deformation, session.endpoints,
                            f" (server {self.server.address}, session {session_id})", twist=session.twist)

    def export(self, volume: Any, deformation: Any, target: Path, *, name: str, options: ExportOptions,
               folded: float | None, session: Any, overwrite: bool, channels: Sequence[Any] = ()
               ) -> Generator[Progress, None, tuple[Path, tuple[str, ...]]]:
        from ._remote import export_iter, upload_iter
        from ._steps import check_folds

        self.check_export(deformation)
        known = self._ids["session"]
        warned = check_folds(deformation, folded=folded, options=options)  # the one fold rule, before any job
        volume_id = yield from self._volume_id(volume, name)
        uploaded = self._ids.setdefault("channels", {})  # each channel uploaded once per scan
        ids = {}
        for ch in channels:
            label = str(ch.metadata["channel"])
            key = (label, ch.source, tuple(ch.shape), ch.data.name)
            if key not in uploaded:
                uploaded[key] = yield from upload_iter(self.server, ch, name=label)
            ids[label] = uploaded[key]
        written = yield from export_iter(self.server, volume_id, known[0], target, options=options,
                                         overwrite=overwrite, channels=ids or None,
                                         scan_name=str(volume.metadata.get("channel") or name) if ids else "")
        return Path(written), (warned,) if warned else ()


class Workflow:
    """The state of one straightening and its steps (see the module's docstring).

    Parameters
    ----------
    backend : Backend, optional
        Where the steps run (default :class:`LocalBackend`).
    options : PipelineOptions, optional
        The pipeline's options (its defaults in one place).

    Signals
    -------
    scan_changed(volume), features_changed(features), selection_changed(selection), ends_changed(ends),
    isovalue_changed(isovalue or None), skeleton_changed(Skeletonized), exported(path, warnings),
    backend_changed(backend)
    """

    scan_changed = Signal(object)
    features_changed = Signal(object)
    selection_changed = Signal(object)
    ends_changed = Signal(object)
    isovalue_changed = Signal(object)
    skeleton_changed = Signal(object)
    exported = Signal(object, object)
    backend_changed = Signal(object)

    def __init__(self, backend: Backend | None = None, *, options: PipelineOptions | None = None) -> None:
        self.backend: Backend = backend or LocalBackend()
        self.options = options or PipelineOptions()
        self.edit = EditModel()
        self.volume: Any = None
        self.name = "scan"
        self.tree: Any = None
        self.features: Any = None
        self.selection = Selection()
        self.ends: Any = None  # session.Endpoints
        self.skeleton: Skeletonized | None = None
        self.twist: Any = None  # session.TwistProfile: as the skeleton set it (or a reopened session recorded it)
        self.source_info: Any = None  # SourceInfo of the scan, once its checksum is known

    # ---- backend and scan ---------------------------------------------------------------------------------------
    def set_backend(self, backend: Backend) -> None:
        """Run the next steps with ``backend``; what the old one held (a server's ids) is dropped."""
        self.backend.forget()
        self.backend = backend
        self.backend_changed.emit(backend)

    def set_scan(self, volume: Any, *, name: str = "scan") -> None:
        """A new scan: the segmentation, selection, ends and skeleton of another scan are dropped."""
        changed = (self.volume is None or volume.source != self.volume.source
                   or tuple(volume.shape) != tuple(self.volume.shape))
        self.volume, self.name = volume, name
        if changed:
            self.backend.forget()
            self.tree = self.features = self.skeleton = self.ends = self.source_info = self.twist = None
            self.selection = Selection(options=self.options.segment)
        self.scan_changed.emit(volume)

    def _need_scan(self) -> Any:
        if self.volume is None:
            raise InvalidInputError("there is no scan yet: pick an Image layer or open a file (step 1)")
        return self.volume

    # ---- segmentation and selection ------------------------------------------------------------------------------
    def segment_task(self, *, level: int | None = None, k: int | None = None) -> Task:
        """Build the join tree (at pyramid ``level``, default the options' level) and simplify it to ``k``."""
        volume, seg = self._need_scan(), self.options.segment
        level = seg.level if level is None else level
        k = int(k or seg.k)
        backend, name = self.backend, self.name

        def make() -> Generator[Progress, None, tuple[Any, Any]]:
            tree, features = yield from backend.segment(volume, name=name, level=level, smooth=seg.smooth, k=k)
            return tree, features if features is not None else tree.simplify(k)

        def apply(value: tuple[Any, Any]) -> None:
            tree, features = value
            self.tree = tree
            self.set_features(features)

        return Task("building the join tree" + ("" if isinstance(backend, LocalBackend) else f" ({backend.label})"),
                    make, apply)

    def set_features(self, features: Any) -> None:
        """New features (a simplification of the tree): the clicked seeds choose again among them."""
        self.features = features
        seeds = dict(self.selection.seeds)
        if self.selection.mask is None:  # before the event: its handlers may select among the new features
            ids, new_seeds = [], {}
            for p in seeds.values():
                i = int(features.ids_at([p])[0])
                if i:
                    ids.append(i)
                    new_seeds[i] = p
            self.select(ids, seeds=new_seeds)
        self.features_changed.emit(features)

    def select(self, ids: list[int], *, seeds: dict[int, tuple] | None = None) -> Selection:
        """Select features of the current segmentation by id (``seeds``: the voxels clicked, default each
        feature's maximum); an empty list clears the selection."""
        f = self.features
        if f is None:
            raise InvalidInputError("segment the scan first (step 2)")
        ids = sorted({int(i) for i in ids if int(i) != 0})
        for i in ids:
            f.stat(i)  # raises for an unknown id
        seeds = seeds or {}
        full = {i: tuple(float(c) for c in seeds.get(i, f.stat(i).max_position_full)) for i in ids}
        self.selection = Selection(features=f, ids=tuple(ids), seeds=full, options=self.options.segment)
        self.selection_changed.emit(self.selection)
        return self.selection

    def pick(self, voxel: Any, *, add: bool = False) -> int:
        """Select the feature at a full-resolution voxel (``add``: to the selection); returns its id (0: none)."""
        f = self.features
        if f is None:
            raise InvalidInputError("segment the scan first (step 2)")
        seed = tuple(float(c) for c in np.asarray(voxel, dtype=float)[-3:])
        fid = int(f.ids_at([seed])[0])
        if fid == 0:
            return 0
        ids = list(self.selection.ids) if add else []
        seeds = {i: self.selection.seeds[i] for i in ids if i in self.selection.seeds}
        if fid not in ids:
            ids.append(fid)
        seeds[fid] = seed
        self.select(ids, seeds=seeds)
        return fid

    def use_mask(self, mask: Any, *, label: int | None = None, key: Any = None, source: Any = None) -> int:
        """Make a mask the selection: an integer or boolean array on the scan's voxel grid, every non-zero voxel
        (``label`` None) or those equal to ``label``. ``source`` is the mask's file (a session records it; None: it
        has none, and a session cannot reopen the selection until it is written, see :meth:`mask_written`).
        Returns the selected voxel count."""
        volume = self._need_scan()
        data = np.asarray(mask)
        if data.shape != tuple(volume.shape):
            raise InvalidInputError(f"the mask has {data.shape} voxels, the scan {tuple(volume.shape)}: a mask must "
                                    "lie on the scan's voxel grid")
        chosen = data == label if label else data != 0
        count = int(np.count_nonzero(chosen))
        if count == 0:
            what = f"label {label}" if label else "any label"
            raise InvalidInputError(f"the mask holds no voxel of {what}: pick another label")
        self.selection = Selection(mask=chosen, key=key if key is not None else (id(mask), label),
                                   options=self.options.segment, label=int(label) if label else None,
                                   source=None if source is None else str(Path(source).absolute()))
        self.selection_changed.emit(self.selection)
        return count

    def mask_written(self, path: Any) -> None:
        """The chosen mask (which had no file, or not these voxels) now lies at ``path``, its chosen voxels non-zero
        and the rest zero: a session records that file, every label of it, from here on."""
        s = self.selection
        if s.mask is None:
            raise InvalidInputError("the selection is not a mask: there is no mask to record")
        self.selection = replace(s, source=str(Path(path).absolute()), label=None)

    def mask_file_task(self, path: Any, *, label: int | None = None) -> Task:
        """Open a mask file (any scan format on the scan's voxel grid; non-zero voxels are the mask) and make it,
        or its ``label``, the selection. The Task's value is ``(labels, notes)`` (:func:`read_mask`: the mask's voxels
        for a Labels layer, and what was done to read them)."""
        volume = self._need_scan()
        path = Path(path)

        def make() -> Generator[Progress, None, Any]:
            yield Progress("open", 0, 1, str(path))
            labels, notes = read_mask(path, volume)
            yield Progress("open", 1, 1)
            return labels, notes

        def apply(value: Any) -> None:
            self.use_mask(value[0], label=label, key=("file", str(path.absolute()), label), source=path)

        return Task("opening the mask", make, apply)

    # ---- the mask's isovalue: grow or shrink a selection of features -------------------------------------------------
    @property
    def isovalue(self) -> float | None:
        """The full-resolution threshold of a selection of features (None: the pipeline's one default rule)."""
        return self.options.segment.isovalue

    def set_isovalue(self, value: float | None) -> None:
        """Threshold the selected features at ``value`` (lower: a larger mask) instead of the default rule (None).
        A chosen mask is taken as it is."""
        from dataclasses import replace

        seg = replace(self.options.segment, isovalue=None if value is None else float(value))
        self.options = replace(self.options, segment=seg)
        self.selection = replace(self.selection, options=seg)
        self.isovalue_changed.emit(seg.isovalue)
        self.selection_changed.emit(self.selection)

    def measure_task(self) -> Task:
        """The selection's full-resolution mask measured: returns ``(voxels, share of the scan, isovalue used)``
        (the isovalue is None for a chosen mask). Off the UI thread: it computes the mask."""
        volume, selection = self._need_scan(), self._need_selection()

        def make() -> Generator[Progress, None, tuple[int, float, float | None]]:
            from .pipeline import SegmentOptions, select_step

            yield Progress("measure", 0, 1, "the selection at full resolution")
            if selection.mask is not None:
                count, iso = int(np.count_nonzero(np.asarray(selection.mask))), None
            else:
                sel = yield from select_step(volume, selection.features, ids=list(selection.ids),
                                             options=selection.options or SegmentOptions())
                count, iso = int(sel.mask.sum().compute()), float(sel.isovalue)
            yield Progress("measure", 1, 1)
            return count, count / max(1, int(np.prod(volume.shape))), iso

        return Task("measuring the selection", make, lambda value: value)

    def intensity_range(self) -> tuple[float, float]:
        """The scan's 0.1 and 99.9 percentiles on its coarsest level (the isovalue slider's range)."""
        volume = self._need_scan()
        data = volume.levels[-1] if len(getattr(volume, "levels", ())) > 1 else volume.data
        step = max(1, int(round((int(np.prod(data.shape)) / 2e6) ** (1 / 3))))
        sample = np.asarray(data[::step, ::step, ::step], dtype=float)
        sample = sample[np.isfinite(sample)]
        if sample.size == 0:
            return 0.0, 1.0
        lo, hi = np.percentile(sample, [0.1, 99.9])
        return float(lo), float(hi if hi > lo else lo + 1)

    def _need_selection(self) -> Selection:
        s = self.selection
        if s.mask is None and (s.features is None or not s.ids):
            raise InvalidInputError("no feature is selected: segment the scan and click the specimen (step 2)")
        return s

    @property
    def has_selection(self) -> bool:
        return self.selection.mask is not None or bool(self.selection.ids)

    def mask(self) -> Any:
        """The selection at full resolution (lazy dask bool array; nothing computed here)."""
        return self._need_selection().full_mask(self._need_scan())

    # ---- ends and skeleton -------------------------------------------------------------------------------------
    def set_ends(self, ends: Any) -> None:
        """The ends (an :class:`~napari_unwind.session.Endpoints`, or None: suggested by the skeleton step)."""
        self.ends = ends
        self.ends_changed.emit(ends)

    def suggest_ends_task(self) -> Task:
        volume, selection, backend, name = self._need_scan(), self._need_selection(), self.backend, self.name

        def make() -> Generator[Progress, None, list]:
            return (yield from backend.suggest_ends(volume, selection, name=name))

        def apply(ends: list) -> None:
            from .session import Endpoints

            self.set_ends(Endpoints(head=tuple(ends[0]), tail=tuple(ends[-1])))

        return Task("suggesting the ends", make, apply)

    def skeleton_task(self) -> Task:
        volume, selection, backend, name = self._need_scan(), self._need_selection(), self.backend, self.name
        ends, options = self.ends, self.options.skeleton

        def make() -> Generator[Progress, None, Skeletonized]:
            return (yield from backend.skeleton(volume, selection, ends, name=name, options=options))

        def apply(result: Skeletonized) -> None:
            self.skeleton = result
            self.twist = result.twist
            if self.ends is None and result.endpoints is not None:
                self.set_ends(result.endpoints)
            self.edit.set_deformation(result.deformation)
            self.skeleton_changed.emit(result)

        return Task("computing the skeleton", make, apply)

    # ---- export and session ------------------------------------------------------------------------------------
    def folded(self) -> float | None:
        """The share of the mask in the deformation's folds, as the last skeleton measured it (None: unknown or
        edited since)."""
        s = self.skeleton
        if s is None or self.edit.deformation is None or s.deformation.to_dict() != self.edit.deformation.to_dict():
            return None
        value = getattr(s.specimen, "folded", None)
        return None if value is None else float(value)

    def export_task(self, target: str | os.PathLike, *, options: ExportOptions | None = None,
                    overwrite: bool = False, channels: Sequence[Any] = ()) -> Task:
        """Straighten the scan with the deformation and write ``target`` (its suffix names the format).

        ``channels``: other images of the scan's grid (Volumes, ``metadata["channel"]`` their names; the scan is
        channel 0, named after the scan), straightened with it in one pass into one multi-channel image (``.zarr``
        or ``.tif``)."""
        from .io._formats import output_format

        volume, d = self._need_scan(), self.edit.deformation
        channels = tuple(channels)
        if channels:
            from .io.channels import CHANNEL_FORMATS, check_same_grid

            fmt = output_format(Path(target).expanduser()) if str(target).strip() else None
            if fmt is not None and fmt not in CHANNEL_FORMATS:
                raise InvalidInputError(f"{Path(target).name}: {fmt} holds one channel; export {len(channels) + 1} "
                                        "channels as OME-Zarr (.ome.zarr) or TIFF (.tif)")
            names = [str(volume.metadata.get("channel") or self.name or "scan"),
                     *[str(c.metadata.get("channel") or f"c{k + 1}") for k, c in enumerate(channels)]]
            if len(set(names)) != len(names):
                raise InvalidInputError(f"two channels have the same name among {names}: rename a layer")
            check_same_grid([volume, *channels], names)
            from dataclasses import replace as _replace

            volume = _replace(volume, metadata={**volume.metadata, "channel": names[0]})
        if d is None:
            raise InvalidInputError("there is no deformation yet: compute the skeleton (step 4) or open a session")
        if not str(target).strip():
            raise InvalidInputError("give the export's path (its suffix names the format, e.g. straight.nrrd)")
        target = Path(target).expanduser()
        output_format(target)
        options = options or self.options.export
        folded, session, backend, name = self.folded(), self.session_or_none(), self.backend, self.name
        backend.check_export(d)

        def make() -> Generator[Progress, None, tuple[Path, tuple[str, ...]]]:
            return (yield from backend.export(volume, d, target, name=name, options=options, folded=folded,
                                              session=session, overwrite=overwrite, channels=channels))

        def apply(value: tuple[Path, tuple[str, ...]]) -> None:
            self.exported.emit(*value)

        return Task("exporting", make, apply)

    def session(self, source: Any) -> Any:
        """The :class:`~napari_unwind.session.Session` of the current state with ``source`` (a SourceInfo)."""
        from .session import Segmentation, Session

        s, seg = self.selection, None
        if s.mask is None and s.features is not None and s.ids:
            seg = Segmentation(k=s.features.k, level=s.features.level, selected=tuple(s.ids),
                               seeds=tuple(s.seeds[i] for i in s.ids))
        elif s.mask is not None and s.source is not None:
            seg = Segmentation(mask=s.source, mask_label=s.label)
        return Session(source=source, deformation=self.edit.deformation, segmentation=seg, endpoints=self.ends,
                       notes="napari-unwind dock", twist=self.twist)

    def session_or_none(self) -> Any:
        """The session written into an export (None: the scan's checksum is not known yet)."""
        if self.source_info is None:
            return None
        try:
            return self.session(self.source_info)
        except InvalidInputError:
            return None
