"""The core's messages in the dock's words (issue 21, item 7).

The pipeline's warnings, reasons and errors end with what to do, said for the command line and the Python API
(``--cage RX,RY``, ``Deformation.set_cage``). :func:`for_dock` swaps that advice for the dock's own controls, so a
user of the dock is never told to pass an option they have no way to give. ``tests/_napari/test_messages.py``
reads every message of the core's sources that gives such advice and checks none reaches the dock untranslated.
"""

from __future__ import annotations

import re

__all__ = ["for_dock"]

_CAGE_SMALLER = "Refine: drag the cage's sides inward in the cross-section, at those s"
_CAGE_LARGER = "Refine: drag the cage's sides outward in the cross-section, at those s"

#: (pattern, the dock's words), applied in order; each pattern is the advice of one core message.
_ADVICE: tuple[tuple[str, str], ...] = (
    # skeleton/_api.py: the deformation folds
    (r"give a smaller cage \(--cage RX,RY, or half_extent=\) or shrink the cages of the keyframes there in the "
     r"session \(Deformation\.set_cage\)", "shrink the cage there (" + _CAGE_SMALLER + ")"),
    # skeleton/_api.py: the cage leaves part of the mask out
    (r"give a larger cage \(--cage RX,RY or --cage-margin\), or edit the keyframes there in the session "
     r"\(Deformation\.set_cage\)", "give a larger cage there (" + _CAGE_LARGER + ")"),
    # pipeline.fold_rule
    (r"shrink the cage there \(unwind skeleton/run --cage RX,RY or --cage-margin M, or Deformation\.set_cage in "
     r"the session\)", "shrink the cage there (" + _CAGE_SMALLER + ")"),
    (r", or allow folds \(--allow-folds\) to export anyway", ", or tick \"allow folds\" (Export) to export anyway"),
    (r"; exported anyway \(allow_folds\)", "; exported anyway (\"allow folds\" is ticked)"),
    # pipeline: a partial specimen
    (r" \(a larger or fitted cage: --cage RX,RY, --cage-margin M\)", " (" + _CAGE_LARGER + ")"),
    # skeleton/_api.py: an end far from the mask
    (r"click inside the specimen, or raise the tolerance \(snap_tolerance, --snap-tolerance\)",
     "drag the end onto the specimen in the \"ends\" layer"),
    # skeleton/_api.py: a specimen in pieces
    (r"give endpoints for every part, in order from head to tail \(Endpoints\.chain, or --chain START END per part "
     r"on the command line\)", "add the start and end of every part to the \"ends\" layer, in order from head to "
     "tail (Ends)"),
    # pipeline.run_job: a fold refused after the session was saved
    (r": edit it, or export it as it is with unwind straighten --session \.\.\. --allow-folds",
     ": edit the keyframes there (Refine), or tick \"allow folds\" (Export)"),
    # skeleton/_api.py: a loop of the body that the path skips where the mask touches itself
    (r", or straighten it as a chain of two parts that meet on the loop \(--chain HEAD P --chain P TAIL, P a point "
     r"on the loop\)", ", or straighten it in two parts that meet on the loop: the head, two points next to each "
     "other on the loop and the tail in the \"ends\" layer, in that order (Ends)"),
    # skeleton/_api.py: a stretch of the body that the path skips between two places where the mask touches itself
    (r", or straighten it as a chain of two parts through that point \(--chain HEAD P --chain P TAIL, P = [^)]*\)",
     ", or straighten it in two parts that meet at that point: the head, two points next to each other there and "
     "the tail in the \"ends\" layer, in that order (Ends)"),
    # skeleton/_api.py: a part cut off that may be a branch or the body running into itself
    (r", or straighten it as a chain of two parts that meet on the part \(--chain HEAD P --chain P TAIL, P a point "
     r"on the part\)", ", or straighten it in two parts that meet on the part: the head, two points next to each "
     "other on the part and the tail in the \"ends\" layer, in that order (Ends)"),
    # pipeline.judge: a branched mask straightened between suggested ends
    (r"; give the head and tail \(--head, --tail\) at the ends of the branch to straighten",
     "; drag the head and tail in the \"ends\" layer to the ends of the branch to straighten (Ends)"),
    # skeleton/_api.py: a line mask
    (r"give the cage's half extents \(--cage RX,RY in [^,]+, half_extent=\) to straighten around the line, or the "
     r"specimen's own mask", "select the specimen's own body (Select), or a mask of it"),
    # skeleton/_twist.py: a round specimen
    (r"give dorsal points or an up direction to set the roll", "turn the keyframes (Refine: twist) to set the roll"),
    # segmentation/_candidates.py: a curved body rejected as not elongated by its principal axes
    (r"; to straighten it, select it \(--select A0,A1,A2\) or give its mask",
     "; to straighten it, click it among the features (step 2, Segment), or choose a mask layer of it"),
    # pipeline: a label map given as the mask
    (r"to straighten one, give its label \(--mask-label N, in Python mask_label=N\)",
     "to straighten one, click that label in the viewer (Segment)"),
    # skeleton/_api.py: separate parts of the mask off the path
    (r"give a mask of this specimen alone, or straighten the parts as one chain \(--chain START END for each part, "
     r"head to tail\)", "choose a mask of this specimen alone (Segment), or add the start and end of every part to "
     "the \"ends\" layer, in order from head to tail (Ends)"),
    # pipeline.judge: the same, in a partial specimen's reason
    (r" \(a mask of this specimen alone, or --chain START END through each part\)",
     " (a mask of this specimen alone, or the start and end of every part in the \"ends\" layer, head to tail)"),
    # warp: the output size limit
    (r"the limit max_output=(\S+) bytes", r"the size limit of \1 bytes"),
    (r", or pass max_output=\.\.\. \(CLI: --max-output\) to raise the limit \(max_output=None: no limit\)",
     ", or choose a coarser spacing (Export)"),
)
_COMPILED = tuple((re.compile(p), r) for p, r in _ADVICE)


def for_dock(message: str) -> str:
    """``message`` with the command line's and the API's advice replaced by the dock's controls."""
    for pattern, words in _COMPILED:
        message = pattern.sub(words.replace("\\", "\\\\"), message)
    return message
