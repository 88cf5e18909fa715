"""The benchmarks' ``--no-NAME`` switches (benchmarks/_util.py ``SWITCHES``) turn a rule of the skeleton off: a
figure "before the rule" in benchmarks/RESULTS.md is only as true as the switch, so a rule renamed or a switch that
sets nothing must fail here rather than measure the code with the rule on."""

from __future__ import annotations

import argparse

import pytest

import napari_unwind.skeleton._api as api
from benchmarks._util import SWITCHES, add_switches, apply_switches


@pytest.mark.parametrize("name", sorted(SWITCHES))
def test_each_switch_sets_its_rules_constants_and_only_when_given(name, monkeypatch):
    constants = SWITCHES[name][1]
    for constant in constants:  # restored after the test
        monkeypatch.setattr(api, constant, getattr(api, constant))
    before = {c: getattr(api, c) for c in constants}
    ap = argparse.ArgumentParser()
    add_switches(ap)
    apply_switches(ap.parse_args([]))
    assert {c: getattr(api, c) for c in constants} == before  # not given: the rule stays on
    apply_switches(ap.parse_args([f"--no-{name}"]))
    for constant, value in constants.items():
        assert getattr(api, constant) == value != before[constant], (constant, before[constant])
