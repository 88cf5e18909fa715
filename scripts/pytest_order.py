"""A pytest plugin for the order check (scripts/test_order.sh), never loaded by the default run.

``--order-seed N`` shuffles the test files, then the tests inside each file, with ``random.Random(N)``;
``--order-reverse`` runs the files and the tests of each file in reverse. Files stay whole so module-scoped
fixtures are built once, as in the default run. ``--order-only DIR`` reorders only the files under DIR, among the
places they hold in the run; every other file keeps its place and its order (CI: the whole suite in one pass, the
GUI tests shuffled inside it).
"""

from __future__ import annotations

import random
from pathlib import Path

import pytest


def pytest_addoption(parser):
    group = parser.getgroup("order", "test order check (scripts/test_order.sh)")
    group.addoption("--order-seed", type=int, default=None, help="shuffle files, then tests in each file")
    group.addoption("--order-reverse", action="store_true", help="reverse the files and the tests in each file")
    group.addoption("--order-only", default=None, metavar="DIR",
                    help="reorder only the files under DIR, in the places they hold; the others keep theirs")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    seed, reverse = config.getoption("--order-seed"), config.getoption("--order-reverse")
    if seed is None and not reverse:
        return
    files: dict[str, list] = {}
    for item in items:
        files.setdefault(str(item.path), []).append(item)
    groups = list(files.values())
    only = config.getoption("--order-only")
    root = Path(only).resolve() if only else None
    slots = [i for i, g in enumerate(groups) if root is None or root in Path(g[0].path).resolve().parents]
    moved = [groups[i] for i in slots]
    if reverse:
        moved = [g[::-1] for g in moved[::-1]]
    else:
        rng = random.Random(seed)
        rng.shuffle(moved)
        for g in moved:
            rng.shuffle(g)
    for i, g in zip(slots, moved):
        groups[i] = g
    items[:] = [it for g in groups for it in g]
    config.pluginmanager.get_plugin("terminalreporter").write_line(
        f"test order: {'reversed' if reverse else f'shuffled with seed {seed}'}"
        + (f" ({len(moved)} files under {only}; the others in their order)" if only else ""))
