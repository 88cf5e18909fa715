"""Step 4, Skeleton: the pipeline's skeleton step on the selection, its status, report and warnings."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from qtpy.QtWidgets import QDoubleSpinBox, QFormLayout, QLabel, QPlainTextEdit, QVBoxLayout

from ...errors import UnwindError
from ...io._volume import unit_label
from .._messages import for_dock
from .._workers import Job
from ._base import Step


def status_line(specimen: Any, where: str = "") -> str:
    """The skeleton's status for the dock: ``skeleton: ok`` or ``skeleton: partial: <the pipeline's reason>``."""
    head = f"skeleton{where}: {specimen.status}"
    return f"{head}: {specimen.reason}" if specimen.reason else head


def folds_line(deformation: Any, folded: float | None, advice: str) -> str:
    """``FOLDS at s = a..b (x % of the mask): <advice>``, or "" when the deformation does not fold."""
    folds = deformation.folds()
    if not folds:
        return ""
    share = "" if folded is None else f" ({100 * folded:.2g} % of the mask)"
    return "FOLDS at s = " + ", ".join(f"{a:.4g}..{b:.4g}" for a, b in folds) + f"{share}: {advice}"


class SkeletonStep(Step):
    """The pipeline's :func:`napari_unwind.pipeline.skeleton_step` (the workflow's options) in a child process
    with progress and Cancel; the status line shows its status by :func:`napari_unwind.pipeline.judge`, the report
    its figures and warnings, and the deformation goes to the editing model."""

    def __init__(self, dock: Any) -> None:
        super().__init__(dock)
        lay = QVBoxLayout(self)
        self.skeleton_need = QLabel("")
        self.skeleton_need.setWordWrap(True)
        lay.addWidget(self.skeleton_need)
        form = QFormLayout()
        self.context = QDoubleSpinBox()
        self.context.setRange(0.0, 1e6)
        self.context.setDecimals(2)
        self.context.setToolTip("widen the straight volume by this much (the scan's unit) beyond the specimen on every "
                                "side and at both ends, to keep what surrounds it; given up where a bend would fold "
                                "the cage, and reported")
        form.addRow("context around the specimen", self.context)
        lay.addLayout(form)
        self.skeleton_button, self.skeleton_cancel = self.job_buttons(lay, "Compute the skeleton", self.run_skeleton)
        self.skeleton_report = QPlainTextEdit()
        self.skeleton_report.setReadOnly(True)
        self.skeleton_report.setPlaceholderText("the skeleton's report and warnings appear here")
        lay.addWidget(self.skeleton_report, 1)

    def update_needs(self) -> None:
        sel = self.dock.has_selection
        self.skeleton_need.setText("" if sel else "Needs a selected feature (step 2); the ends (step 3) are "
                                                  "suggested when there are none.")
        self.skeleton_button.setEnabled(sel)

    def run_skeleton(self) -> Job | None:
        """Estimate the deformation of the selection in a worker (progress, Cancel), here (in a child process) or
        on the server; the model gets it."""
        dock = self.dock
        try:
            dock._check_selection()
            self.workflow.set_ends(dock.endpoints())  # the ends layer as the user left it (None: suggested)
            options = self.workflow.options
            context = float(self.context.value())
            if context != options.skeleton.context:
                self.workflow.options = replace(options, skeleton=replace(options.skeleton, context=context))
            task = self.workflow.skeleton_task()
        except UnwindError as exc:
            self._fail(exc)
            return None
        self.skeleton_report.setPlainText("computing...")

        def done(result: Any) -> None:
            had_ends = dock._ends_layer is not None
            task.apply(result)
            self.skeleton_ready(result, show_ends=not had_ends)

        return dock._start(task.make, task.label, done, (self.skeleton_cancel,))

    def skeleton_ready(self, outcome: Any, *, show_ends: bool = True) -> None:
        """Show a :class:`~napari_unwind.workflow.Skeletonized`: the report, the status line, the suggested ends."""
        specimen, d = outcome.specimen, outcome.deformation
        result = getattr(specimen, "skeleton", None)
        where = outcome.where
        lines = [status_line(specimen), f"length {d.length:.4g} {unit_label(d.unit)}, {len(d)} keyframes"
                 + (" (suggested ends)" if result is not None and result.suggested else "") + where]
        if result is not None:
            lines.append(result.report())
            lines.append(result.twist_report())
            if result.context is not None:
                lines.append(f"context: at least {max(result.context, 0.0):.4g} {unit_label(d.unit)} beyond the "
                             "specimen on every side")
        folds = folds_line(d, specimen.folded, "edit the keyframes there (Refine)")
        if folds:
            lines.append(folds)
        lines += [f"warning: {w}" for w in specimen.warnings]
        self.skeleton_report.setPlainText(for_dock("\n".join(lines)))
        if show_ends and outcome.endpoints is not None:
            self.dock.ends_step.show_session_ends(outcome.endpoints, later=True)  # one layer a turn (issue 21)
        self._say(status_line(specimen) + (" (server)" if where else "")
                  + (" (warnings: see Skeleton)" if specimen.warnings or folds else ""))
