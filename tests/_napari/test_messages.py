"""The dock speaks of its own controls (issue 21, item 7): no message of the core reaches it with the command
line's or the API's advice (``--cage RX,RY``, ``Deformation.set_cage``) untranslated.

The messages are read from the core's sources (every string literal, f-strings with their fields as ``X``), not
listed by hand: a new message with such advice fails here until :mod:`napari_unwind._napari._messages` says it in
the dock's words, or it is listed below as one the dock never shows.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from napari_unwind._napari._messages import for_dock

ROOT = Path(__import__("napari_unwind").__file__).parent
CORE = ["pipeline.py", "warp.py", "deformation.py", "editing.py", "skeleton/*.py", "segmentation/*.py"]
#: advice a dock user cannot act on: an option, an API call, a command
ADVICE = re.compile(r"(?<![\w-])--[a-z][\w-]*|\b(?:Deformation|Endpoints)\.\w+|\bmax_output=|\bhalf_extent=|"
                    r"\bunwind (?:run|skeleton|straighten|segment)\b")
#: messages of the core the dock never shows, each with why
NOT_IN_THE_DOCK = {
    "give a folder for --all": "run --all's output folder (the command line and the server's batch)",
    "choose another folder or pass --overwrite": "run --all's output folder",
    "unwind run --all: feature": "the notes of a session written by run --all",
    "is not a segmentation written by 'unwind segment'": "reading a segmentation file (unwind select)",
}


def _docstrings(tree: ast.AST) -> set[int]:
    ids = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                ids.add(id(first.value))
    return ids


def core_messages() -> list[tuple[str, str]]:
    out = []
    for pattern in CORE:
        for path in sorted(ROOT.glob(pattern)):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            skip = _docstrings(tree)
            inner = {id(v) for node in ast.walk(tree) if isinstance(node, ast.JoinedStr) for v in node.values}
            for node in ast.walk(tree):
                if id(node) in skip or id(node) in inner:
                    continue
                if isinstance(node, ast.JoinedStr):
                    text = "".join(v.value if isinstance(v, ast.Constant) else "X" for v in node.values)
                elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                    text = node.value
                else:
                    continue
                if ADVICE.search(text) and not any(k in text for k in NOT_IN_THE_DOCK):
                    out.append((f"{path.relative_to(ROOT)}:{node.lineno}", text))
    return out


MESSAGES = core_messages()


def test_the_core_has_messages_with_advice():
    """The scan finds the advice it is about (a scan that finds nothing would pass everything)."""
    assert len(MESSAGES) >= 8, MESSAGES
    assert any("Deformation.set_cage" in t for _, t in MESSAGES)


@pytest.mark.parametrize("where, text", MESSAGES, ids=[w for w, _ in MESSAGES])
def test_every_core_message_reaches_the_dock_in_its_words(where, text):
    shown = for_dock(text)
    assert not ADVICE.search(shown), f"{where}: the dock would show {shown!r}"


def test_the_fold_warning_names_the_refine_step():
    text = ("the deformation folds (the cage is wider than the bend's radius) at s = 1-2 mm: give a smaller cage "
            "(--cage RX,RY, or half_extent=) or shrink the cages of the keyframes there in the session "
            "(Deformation.set_cage)")
    assert for_dock(text) == ("the deformation folds (the cage is wider than the bend's radius) at s = 1-2 mm: "
                              "shrink the cage there (Refine: drag the cage's sides inward in the cross-section, "
                              "at those s)")


def test_the_skipped_stretch_names_the_ends_layer_with_its_point():
    text = ("the mask touches itself between the ends: the path crosses where two turns touch and skips a stretch of "
            "the body through [27.0, 33.0, 61.0] (voxels), 34 % of the mask, which lies in the straight volume beside "
            "the path, not straightened; separate the touching turns in the mask, or straighten it as a chain of two "
            "parts through that point (--chain HEAD P --chain P TAIL, P = [27.0, 33.0, 61.0])")
    shown = for_dock(text)
    assert shown.endswith("separate the touching turns in the mask, or straighten it in two parts that meet at that "
                          "point: the head, two points next to each other there and the tail in the \"ends\" layer, "
                          "in that order (Ends)"), shown
    assert "through [27.0, 33.0, 61.0] (voxels)" in shown
