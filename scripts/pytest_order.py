"""A pytest plugin for the order check (scripts/test_order.sh), never loaded by the default run.

``--order-seed N`` shuffles the test files, then the tests inside each file, with ``random.Random(N)``;
``--order-reverse`` runs the files and the tests of each file in reverse. Files stay whole so module-scoped
fixtures are built once, as in the default run.
"""

from __future__ import annotations

import random

import pytest


def pytest_addoption(parser):
    group = parser.getgroup("order", "test order check (scripts/test_order.sh)")
    group.addoption("--order-seed", type=int, default=None, help="shuffle files, then tests in each file")
    group.addoption("--order-reverse", action="store_true", help="reverse the files and the tests in each file")


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(config, items):
    seed, reverse = config.getoption("--order-seed"), config.getoption("--order-reverse")
    if seed is None and not reverse:
        return
    files: dict[str, list] = {}
    for item in items:
        files.setdefault(str(item.path), []).append(item)
    groups = list(files.values())
    if reverse:
        groups = [g[::-1] for g in groups[::-1]]
    else:
        rng = random.Random(seed)
        rng.shuffle(groups)
        for g in groups:
            rng.shuffle(g)
    items[:] = [it for g in groups for it in g]
    config.pluginmanager.get_plugin("terminalreporter").write_line(
        f"test order: {'reversed' if reverse else f'shuffled with seed {seed}'}")
