"""No module of the package imports another that imports it back (issue 10, item 8: cli <-> demo,
io/stack <-> io/tiff, segmentation/_features <-> _jointree were such circles)."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "napari_unwind"


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """Modules of the package that ``path`` imports anywhere (inside functions too)."""
    here = _module_name(path).split(".")
    package = here if path.name == "__init__.py" else here[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
                names = [f"{target}.{a.name}" for a in node.names]
            else:
                target, names = node.module or "", [f"{node.module}.{a.name}" for a in node.names]
            out.update(n for n in [target, *names] if n in modules)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in modules)
    return out


def _pairs() -> list[tuple[str, str]]:
    files = {_module_name(p): p for p in PKG.rglob("*.py")}
    graph = {m: _imports(p, set(files)) - {m} for m, p in files.items()}
    # a package importing its own submodules (re-exports) is not a circle of two modules
    return sorted((a, b) for a in graph for b in graph[a]
                  if a < b and a in graph.get(b, set()) and not (b.startswith(a + ".") or a.startswith(b + ".")))


#: None left: the command line's argument helpers moved down to _cliargs, below cli and _cli_remote.
KNOWN: list[tuple[str, str]] = []


def test_no_two_modules_import_each_other():
    assert _pairs() == KNOWN


def test_the_detector_sees_a_circle(tmp_path, monkeypatch):
    """The check can fail: two modules importing each other are reported."""
    pkg = tmp_path / "napari_unwind"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from .b import g\n")
    (pkg / "b.py").write_text("from napari_unwind import a\n")
    monkeypatch.setattr(__import__(__name__), "PKG", pkg, raising=False)
    globals()["PKG"] = pkg
    try:
        assert _pairs() == [("napari_unwind.a", "napari_unwind.b")]
    finally:
        globals()["PKG"] = Path(__file__).resolve().parents[1] / "napari_unwind"
