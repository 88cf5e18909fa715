"""What the installed distribution provides, seen from outside the source tree."""

import subprocess
import sys


def _probe(code, cwd):
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=cwd)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_service_code_has_its_own_import_name(tmp_path):
    out = _probe(
        "import importlib.util as u; "
        "print(u.find_spec('services') is None, u.find_spec('unwind_services') is not None)",
        tmp_path,
    )
    assert out == "True True"


def test_version_and_public_api(tmp_path):
    out = _probe(
        "import napari_unwind as n; from importlib.metadata import version; "
        "print(n.__version__ == version('napari-unwind'), all(hasattr(n, x) for x in n.__all__))",
        tmp_path,
    )
    assert out == "True True"


def test_every_subpackage_is_listed_for_the_wheel():
    """pyproject lists packages explicitly (services/ maps to unwind_services); a new subpackage must be added."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    listed = set(tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(root).parts) for p in (root / "napari_unwind").rglob("__init__.py")}
    services = root / "services" / "unwind_services"
    found |= {".".join(("unwind_services", *p.parent.relative_to(services).parts))
              for p in services.rglob("__init__.py")}
    assert found == listed
