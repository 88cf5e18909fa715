"""The Unwind dock: the whole workflow in one widget, from a scan to an exported straight specimen.

Steps (pages of a tool box, revisitable in any order; each says what it still needs):

Scan
    An Image layer of the viewer, or a file opened with :func:`napari_unwind.io.open_volume`; shape, spacing and
    unit, and a warning when the spacing is missing (no unit and 1 x 1 x 1: lengths are then in voxels). The
    "backend" row above it: "this computer", or "server" (address, token or token file, CA file for TLS; Connect
    checks health and the token; "path on server" names a scan the server already holds, which is then registered
    there instead of uploaded). On a server the segmentation, the ends, the skeleton and the export run through
    :class:`napari_unwind.client.Client` (:mod:`napari_unwind._remote`): the scan is uploaded once, the features'
    label volume comes back to draw and pick, the selection's mask is made there (a Select job), the export is
    downloaded to the chosen path; same progress bar and Cancel (which cancels the server's job).
Segment
    The join tree is built once in a worker (Cancel stops it); the feature-count slider re-simplifies it live (no
    rebuild; on a server the server simplifies its cached tree and sends the label volume). The features are a
    Labels layer; a click on one (2D or 3D) selects it, shift-click adds it; the table lists their statistics and
    shows the selection, which is also a Labels layer ``"selection"``.
Ends
    Suggested head and tail (:func:`napari_unwind.skeleton.suggest_endpoints`) in a Points layer ``"ends"``:
    drag them in select mode, place more in add mode. Two points are head and tail; more are read in order as a
    chain (start and end of each part, head to tail) for a specimen in pieces.
Skeleton
    The pipeline's :func:`napari_unwind.pipeline.skeleton_step` (options: ``self.options.skeleton``, a
    :class:`~napari_unwind.pipeline.PipelineOptions`) in a child process with progress and Cancel; the status line
    shows its status by :func:`napari_unwind.pipeline.judge` (``ok``, or ``partial`` with the reason, e.g. coverage
    under 0.99), the report its figures and warnings, and the deformation goes to the editing model.
Refine
    The cross-section editor (:class:`napari_unwind._napari._refine.RefinePanel`) on the same model.
Export
    Format, spacing, order, padding, "allow folds" and path (the fields start at the pipeline's
    :class:`~napari_unwind.pipeline.ExportOptions` defaults); :func:`napari_unwind.pipeline.export_step` in a worker
    with progress and Cancel: the one fold rule (a fold over the specimen is refused with the command line's
    message unless "allow folds" is ticked), then the writer; the result opens as a layer. Saving is explicit; an
    existing file is replaced only after confirmation.
Session
    Save and load (:mod:`napari_unwind.session`) at any step.

Each step is a small widget in its own module of :mod:`._steps` (its controls and handlers); this module is
their container: the pages, the job runner and the status line, the layers the steps share, and the workflow's
event wiring. The dock's public methods (``segment``, ``pick``, ``export``, ``save_session``...) are its scriptable
API and hand over to the step that owns them.

The dock's steps call the one pipeline (:mod:`napari_unwind.pipeline`, through the Qt-free
:mod:`napari_unwind._steps`) with its option objects (no default is restated here), the core and the
:class:`~napari_unwind.editing.EditModel`; every long job runs in a ``thread_worker`` (:mod:`._workers`), so the UI
never waits on one.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any

from qtpy.QtWidgets import QLabel, QToolBox, QVBoxLayout, QWidget

from ..errors import InvalidInputError, UnwindError
from ..pipeline import ExportOptions
from ..progress import Progress
from ..workflow import LocalBackend, Workflow
from . import _docks, _gc
from ._messages import for_dock
from ._steps import (
    DOCK_SHORTCUTS,
    EndsStep,
    ExportStep,
    ScanStep,
    SegmentStep,
    SessionStep,
    ShortcutsStep,
    SkeletonStep,
    refine_page,
)
from ._steps._base import SKELETON as _SKELETON  # noqa: F401 - the name the tests check
from ._steps.ends import ends_size
from ._steps.export import EXPORT_FORMATS
from ._steps.scan import volume_from_layer
from ._steps.skeleton import status_line as _status_line  # noqa: F401 - the name the tests read
from ._workers import Job, JobCancelled, in_child, start_job, start_process_job

__all__ = ["DOCK_SHORTCUTS", "EXPORT_FORMATS", "UnwindWidget", "ends_size", "volume_from_layer"]


#: what napari imports on the UI thread for the dock's first Labels layer (its features table: pandas, with pyarrow
#: and dateutil; 1.2-1.5 s of the segment step's result without bytecode caches, issue 21)
WARM_IMPORTS = ("pandas",)
_WARM_STARTED: list[bool] = []


def _warm_dashes() -> None:
    """vispy's dash patterns of its agg lines (module-level lru_cache; 13 patterns of 1024 argmins each, ~80 ms of
    the first Labels layer's insert: napari's polygon overlay of a Labels layer draws one)."""
    from vispy.visuals.line.dash_atlas import DashAtlas

    DashAtlas()


def _warm_imports() -> None:
    """Import :data:`WARM_IMPORTS` and make vispy's dash patterns in a background thread, once per process, while
    the user opens a scan (the import lock makes a UI thread that needs one meanwhile wait for it rather than import
    it again)."""
    import threading

    if _WARM_STARTED:
        return
    _WARM_STARTED.append(True)

    def run() -> None:
        import importlib

        for name in WARM_IMPORTS:
            try:
                importlib.import_module(name)
            except ImportError:  # napari imports it later or does without
                pass
        try:
            _warm_dashes()
        except Exception:  # noqa: BLE001 - another vispy: the first Labels layer pays it as before
            pass

    threading.Thread(target=run, name="unwind-warm-imports", daemon=True).start()
    threading.Thread(target=_warm_kernels, name="unwind-warm-kernels", daemon=True).start()


def _warm_kernels() -> None:
    """Fill numba's cache with the kernels of the dock's steps in a child process (:mod:`napari_unwind._warm`): a
    first call in this process would compile here and stall the UI thread 0.2-0.4 s. Not counted in ``idle``: the
    dock works meanwhile (a step that comes first compiles in this process, as without it)."""
    from .._warm import warm_in_child

    warm_in_child()


def _warming() -> bool:
    """True while :func:`_warm_imports` runs (its imports; the kernels: :func:`warming_kernels`)."""
    import threading

    return any(t.name == "unwind-warm-imports" for t in threading.enumerate())


def warming_kernels() -> bool:
    """True while the child of :func:`_warm_kernels` fills numba's cache."""
    import threading

    return any(t.name == "unwind-warm-kernels" for t in threading.enumerate())


class UnwindWidget(QWidget):
    """The Unwind dock (see the module docstring): the step widgets of :mod:`._steps` on a tool box over one
    :class:`~napari_unwind.workflow.Workflow`.

    Parameters
    ----------
    napari_viewer : napari.Viewer
        The viewer whose layers the dock reads and writes.
    """

    def __init__(self, napari_viewer: Any, parent: QWidget | None = None) -> None:
        super().__init__(parent)
        from . import _private

        _private.memoise_program_parse()  # each new layer's first paint parses no GLSL it has parsed before
        _warm_imports()
        self.viewer = napari_viewer
        _gc.engage(self)  # full collections skip the heap that survived one while the viewer is open (_gc.py)
        #: The workflow's state and steps (Qt-free); the steps show it and turn clicks into its calls. Its
        #: backend runs the steps on this computer (the skeleton in a child process) or on a server.
        self.workflow = Workflow(LocalBackend(runner=in_child))
        self.model = self.workflow.edit
        #: the layers the steps share: the scan's, the features', the selection's, the ends'
        self.scan_layer: Any = None
        self._features_layer: Any = None
        self._selection_layer: Any = None
        self._ends_layer: Any = None
        #: the Labels layer whose mask is the selection: (layer, label; None: every label), or None
        self.mask_choice: tuple[Any, int | None] | None = None
        self.job: Job | None = None

        self.toolbox = QToolBox()
        # the steps take the dock's height: napari adds a stretch under a dock with no vertically expanding
        # widget, weighted by how many docks the process opened before (the 4th got the open step ~50 px tall)
        policy = self.toolbox.sizePolicy()
        policy.setVerticalPolicy(policy.Policy.Expanding)
        self.toolbox.setSizePolicy(policy)
        self.scan_step = ScanStep(self)
        self.segment_step = SegmentStep(self)
        self.ends_step = EndsStep(self)
        self.skeleton_step = SkeletonStep(self)
        refine, self.refine_panel = refine_page(self.viewer, self.model, lambda: self.volume)
        self.export_step = ExportStep(self)
        self.session_step = SessionStep(self)
        self.shortcuts_step = ShortcutsStep(self, self.refine_panel)
        self.steps = (self.scan_step, self.segment_step, self.ends_step, self.skeleton_step, self.export_step,
                      self.session_step, self.shortcuts_step)
        for page, title in ((self.scan_step, "1. Scan"), (self.segment_step, "2. Segment"),
                            (self.ends_step, "3. Ends"), (self.skeleton_step, "4. Skeleton"), (refine, "5. Refine"),
                            (self.export_step, "6. Export"), (self.session_step, "7. Session"),
                            (self.shortcuts_step, "Shortcuts")):
            self.toolbox.addItem(page, title)
        self.status = QLabel("")
        self.status.setWordWrap(True)
        layout = QVBoxLayout(self)
        layout.addWidget(self.toolbox, 1)  # the open step gets the height; the status line only its own
        layout.addWidget(self.status)
        self.setMinimumWidth(400)  # the feature table and the reports need room; napari's docks start narrow

        # the workflow's events
        self.workflow.features_changed.connect(self.segment_step.features_ready)
        self.workflow.selection_changed.connect(self.segment_step.show_selection)
        self.model.deformation_changed.connect(self._on_deformation_changed)
        self.viewer.layers.events.inserted.connect(self._on_layers_changed)
        self.viewer.layers.events.removed.connect(self._on_layers_changed)
        _docks.register(self.viewer, self)  # a session opened by napari's reader leaves its selection to us
        self.scan_step.refresh_layer_combo()
        self._update_needs()

    # the workflow's state, under the names the dock's views and tests read
    volume = property(lambda self: self.workflow.volume)
    tree = property(lambda self: self.workflow.tree)
    features = property(lambda self: self.workflow.features)
    selected = property(lambda self: list(self.workflow.selection.ids))
    seeds = property(lambda self: dict(self.workflow.selection.seeds))

    @property
    def options(self) -> Any:
        """The pipeline's options (napari_unwind.pipeline: every default once); the export page's fields and the
        "allow folds" box override its export part when an export starts."""
        return self.workflow.options

    @options.setter
    def options(self, value: Any) -> None:
        self.workflow.options = value

    specimen = property(lambda self: None if self.workflow.skeleton is None else self.workflow.skeleton.specimen)
    result = property(lambda self: None if self.specimen is None else getattr(self.specimen, "skeleton", None))
    #: the last file exported (None: nothing yet)
    exported = property(lambda self: self.export_step.exported)

    @property
    def server(self) -> Any:
        """The server the steps run on (a ServerBackend's), or None: this computer."""
        return getattr(self.workflow.backend, "server", None)

    @property
    def where(self) -> str:
        """``" (server)"`` after what a server did, "" on this computer."""
        return "" if self.server is None else " (server)"

    @property
    def _remote(self) -> dict[str, Any]:
        """The server's ids of this scan (volume, segmentation, mask, session); empty on this computer."""
        return getattr(self.workflow.backend, "_ids", {})

    @property
    def has_selection(self) -> bool:
        """The workflow has a selection, and the mask layer chosen as the selection (if any) is still there."""
        return self.workflow.has_selection and (self.mask_choice is None or self.mask_choice[0] in self.viewer.layers)

    # ==============================================================================================================
    # the dock's scriptable API: each call goes to the step that owns it
    # ==============================================================================================================
    def connect_server(self) -> Job | None:
        """Check the server's health and the token; on success the dock's jobs run there (step 1)."""
        return self.scan_step.connect_server()

    def use_layer(self, layer: Any) -> None:
        """Make an Image layer the scan (step 1)."""
        self.scan_step.use_layer(layer)

    def open_scan(self, path: str | os.PathLike, *, then: Callable[[], Any] | None = None) -> Job | None:
        """Open a scan file (lazily, in a worker) and add it as an Image layer; it becomes the scan (step 1)."""
        return self.scan_step.open_scan(path, then=then)

    def segment(self, *, level: int | None = None) -> Job | None:
        """Build the join tree of the scan in a worker and show its features (step 2)."""
        return self.segment_step.segment(level=level)

    def set_feature_count(self, k: int) -> None:
        """Re-simplify the tree to ``k`` features, off the UI thread (step 2)."""
        self.segment_step.set_feature_count(k)

    def pick(self, position: Any, *, view_direction: Any = None, dims_displayed: Any = None,
             add: bool = False) -> int:
        """Select the feature at a world position (2D: the point; 3D: along the view ray); return its id (0: none)."""
        return self.segment_step.pick(position, view_direction=view_direction, dims_displayed=dims_displayed,
                                      add=add)

    def select_features(self, ids: list[int], *, seeds: dict[int, tuple] | None = None) -> None:
        """Set the selection (feature ids of the current segmentation); shown in the table and the layer."""
        self.segment_step.select_features(ids, seeds=seeds)

    def set_isovalue(self, value: float | None) -> None:
        """Threshold the selected features at ``value`` (None: the pipeline's default rule)."""
        self.segment_step.set_isovalue(value)

    def use_labels(self, layer: Any, *, label: int | None = None, at: Any = None) -> int:
        """Make a Labels layer the selection: every labelled voxel, one ``label``, or the label under ``at``."""
        return self.segment_step.use_labels(layer, label=label, at=at)

    def open_mask(self, path: str | os.PathLike, *, label: int | None = None) -> Job | None:
        """Open a mask file as a Labels layer over the scan and make it (or its ``label``) the selection."""
        return self.segment_step.open_mask(path, label=label)

    def mask(self) -> Any:
        """The selection at full resolution (lazy dask bool array): the chosen mask, or the selected features
        through the pipeline's select_step with the dock's segmentation options (nothing is computed here)."""
        self._check_selection()
        return self.workflow.mask()

    def suggest_ends(self) -> Job | None:
        """Suggest head and tail on the selection's mask and show them in the "ends" layer (step 3)."""
        return self.ends_step.suggest_ends()

    def set_ends(self, voxels: list, roles: list[str] | None = None) -> Any:
        """Show ends (full-resolution voxel coordinates, head first) in the "ends" Points layer."""
        return self.ends_step.set_ends(voxels, roles)

    def endpoints(self) -> Any:
        """The ends layer's points as an :class:`~napari_unwind.session.Endpoints` (None: no ends layer)."""
        return self.ends_step.endpoints()

    def run_skeleton(self) -> Job | None:
        """Estimate the deformation of the selection in a worker; the model gets it (step 4)."""
        return self.skeleton_step.run_skeleton()

    def export_options(self) -> ExportOptions:
        """The pipeline's export options with the export page's fields (spacing, order, padding, allow folds)."""
        return self.export_step.export_options()

    def confirm_overwrite(self, path: Path) -> bool:
        """Ask before replacing an existing file (saving is explicit, never on close)."""
        return self.export_step.confirm_overwrite(path)

    def export(self, path: str | os.PathLike) -> Job | None:
        """Straighten the scan with the model's deformation and write ``path``; the file opens as a layer (step 6)."""
        return self.export_step.export(path)

    def save_session(self, path: str | os.PathLike) -> Job | None:
        """Save the current state as a session (step 7)."""
        return self.session_step.save_session(path)

    def load_session(self, path: str | os.PathLike) -> Job | None:
        """Open a session: its scan, the ends, the deformation and the selection (step 7)."""
        return self.session_step.load_session(path)

    # ==============================================================================================================
    # jobs and messages
    # ==============================================================================================================
    def _start(self, make: Callable[[], Generator[Progress, None, Any]] | None, label: str,
               on_returned: Callable[[Any], Any], cancel_buttons: tuple = (), *,
               process: tuple | None = None) -> Job | None:
        """Start a job: ``make()`` in a thread worker, or ``process = (fn, args, kwargs)`` in a child process."""
        if self.job is not None and self.job.running:
            self._fail(InvalidInputError(f"{self.job.label} is still running: wait for it or cancel it first"))
            return None
        for b in cancel_buttons:
            b.setEnabled(True)

        def returned(value: Any) -> None:
            try:
                on_returned(value)
            except Exception as exc:  # noqa: BLE001 - shown in the dock, never a traceback dialog
                self._fail(exc)

        def finished() -> None:
            for b in cancel_buttons:
                b.setEnabled(False)
            self._update_needs()
            _gc.soon()  # what the job left behind in reference cycles: collected once the docks are idle

        self._say(f"{label}...")
        callbacks = dict(label=label, on_returned=returned, on_error=self._fail, on_finished=finished)
        if process is not None:
            self.job = start_process_job(*process, **callbacks)
        else:
            self.job = start_job(make, **callbacks)
        return self.job

    @property
    def idle(self) -> bool:
        """No job running, no re-simplification or measurement of the selection, and nothing left for the Refine
        panel's straight preview."""
        from . import _reveal

        preview = getattr(self.refine_panel, "preview", None)
        return ((self.job is None or self.job.done) and not self.segment_step.busy
                and bool(getattr(preview, "idle", True)) and not _reveal.pending() and not _warming())

    def cancel(self) -> None:
        """Cancel the running job (it stops at its next progress step)."""
        if self.job is not None and self.job.running:
            self.job.cancel()
            self._say(f"cancelling {self.job.label}...")

    def _say(self, text: str) -> None:
        self.status.setStyleSheet("")
        self.status.setText(for_dock(text))

    def _fail(self, exc: BaseException) -> None:
        if isinstance(exc, JobCancelled):
            self._say(f"{self.job.label if self.job else 'the job'} was cancelled")
            return
        text = str(exc) if isinstance(exc, (UnwindError, FileNotFoundError)) else f"{type(exc).__name__}: {exc}"
        self.status.setStyleSheet("color: #ff5050")
        self.status.setText(f"error: {for_dock(text)}")

    # ==============================================================================================================
    # the layers the steps share
    # ==============================================================================================================
    def _on_layers_changed(self, event: Any = None) -> None:
        self.scan_step.refresh_layer_combo()
        self.segment_step.refresh_mask_combo()
        self.export_step.channels_box.update_layers()
        layer = getattr(event, "value", None)
        if event is not None and getattr(event, "type", "") == "removed":
            if layer is self.scan_layer:
                self.scan_layer = None
            for name in ("_features_layer", "_selection_layer", "_ends_layer"):
                if getattr(self, name) is layer:
                    setattr(self, name, None)
            self._update_needs()
        elif layer is not None:
            self._adopt(layer)

    def _adopt(self, layer: Any) -> None:
        """Pick up what a session opened by napari's reader restores (ends, deformation) when the dock has none."""
        meta = (getattr(layer, "metadata", None) or {}).get("napari_unwind", {})
        if "deformation" in meta and self.model.deformation is None:
            from ..deformation import Deformation

            try:
                self.model.set_deformation(Deformation.from_dict(meta["deformation"]))
            except UnwindError as exc:
                self._fail(exc)
        if "endpoints" in meta and self._ends_layer is None:
            self._ends_layer = layer
        if "selected" in meta and self._selection_layer is None:
            self._selection_layer = layer  # the reader's selection: the dock updates it rather than add another
        if meta.get("selection_mask") and self.scan_layer is not None and not self.has_selection:
            self.use_labels(layer, label=meta.get("mask_label"))  # a session whose selection was a mask file
        if self.scan_layer is None and "session_path" in meta and layer in self.scan_step.image_layers():
            self.use_layer(layer)
            seg = meta.get("segmentation")
            if seg and seg.get("k") and (seg.get("selected") or seg.get("seeds")) and self.tree is None:
                from ..session import Segmentation

                self.segment_step.resume(Segmentation.from_dict(seg))  # recomputed in a worker

    def _set_scan(self, volume: Any, layer: Any) -> None:
        """Make ``volume`` (shown by ``layer``) the scan (step 1 shows it)."""
        self.scan_step.set_scan(volume, layer)

    def _add_layer(self, layer_tuple: Any, *, reveal: bool = False) -> Any:
        """Add a layer from a layer-data tuple (or a napari Layer made in a worker). ``reveal``: added hidden and
        shown on the next turn of the event loop (:mod:`._reveal`: napari's insert and the first paint of the new
        visual in two UI stalls, not one)."""
        from napari.layers import Layer

        layer = layer_tuple if isinstance(layer_tuple, Layer) else Layer.create(*layer_tuple)
        if reveal:
            from . import _reveal

            return _reveal.add_layer(self.viewer, layer)
        self.viewer.add_layer(layer)
        return layer

    def _put_layer(self, attr: str, layer_tuple: tuple) -> Any:
        """Update the dock's layer ``attr`` with new data and geometry, or add it when it is gone: made now, put
        into the viewer hidden as a step and shown as the next (:mod:`._reveal`: the segment step's result makes two
        layers, each insert and first paint on its own turn; the active layer stays)."""
        from napari.layers import Layer

        from . import _reveal

        data, meta, _ = layer_tuple
        layer = getattr(self, attr)
        if layer is not None and (layer in self.viewer.layers or _reveal.waiting(layer)):
            layer.data = data
            for key in ("scale", "translate"):
                if key in meta:
                    setattr(layer, key, meta[key])
        else:
            layer = Layer.create(*layer_tuple)
            _reveal.add_layer(self.viewer, layer, now=False, keep_active=True)
            setattr(self, attr, layer)
            self.segment_step.refresh_mask_combo()  # the dock's own layers are no masks to choose
            from ._layers import in_3d

            in_3d(self.viewer, layer)  # in 3D a coarse stand-in: napari's ray caster froze software GL
        return layer

    def _check_selection(self) -> None:
        """Raise when there is no selection (or its chosen mask layer was removed: the selection is then cleared)."""
        if self.mask_choice is not None and self.mask_choice[0] not in self.viewer.layers:
            self.mask_choice = None
            self.workflow.select([]) if self.features is not None else None
            raise InvalidInputError("the mask layer chosen as the selection was removed: choose another mask "
                                    "or click a feature (step 2)")
        if not self.workflow.has_selection:
            raise InvalidInputError("no feature is selected: segment the scan and click the specimen (step 2)")

    # ==============================================================================================================
    # what each step needs
    # ==============================================================================================================
    def _on_deformation_changed(self, d: Any) -> None:
        self._update_needs()

    def _update_needs(self) -> None:
        for step in self.steps:
            step.update_needs()
