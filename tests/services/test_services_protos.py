"""The contracts: stubs are current, every message, field, enum value and rpc is commented, enums start at 0."""

from __future__ import annotations

import filecmp
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PROTOS = sorted((ROOT / "protos" / "unwind" / "v1").glob("*.proto"))
STUBS = ROOT / "services" / "unwind_services" / "_proto"


def test_committed_stubs_are_what_the_script_generates(tmp_path):
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import gen_protos
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    gen_protos.generate(tmp_path)
    fresh = {p.relative_to(tmp_path) for p in tmp_path.rglob("*.py*")}
    committed = {p.relative_to(STUBS) for p in STUBS.rglob("*.py*") if "__pycache__" not in p.parts}
    assert fresh == committed, f"stale stubs: run scripts/gen_protos.py ({fresh ^ committed})"
    stale = [str(r) for r in sorted(fresh) if not filecmp.cmp(tmp_path / r, STUBS / r, shallow=False)]
    assert not stale, f"stale stubs, run scripts/gen_protos.py: {stale}"


def test_the_stale_check_can_fail(tmp_path):
    """A changed comment changes the generated descriptor: the comparison above notices."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        import gen_protos
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    proto_root = tmp_path / "protos"
    (proto_root / "unwind" / "v1").mkdir(parents=True)
    for p in PROTOS:
        text = p.read_text()
        if p.name == "common.proto":
            text = text.replace("double axis2 = 3;", "double axis2 = 3;\n  // an added field\n  double w = 4;")
        (proto_root / "unwind" / "v1" / p.name).write_text(text)
    old = gen_protos.PROTO_ROOT
    gen_protos.PROTO_ROOT = proto_root
    try:
        gen_protos.generate(tmp_path / "out")
    finally:
        gen_protos.PROTO_ROOT = old
    assert not filecmp.cmp(tmp_path / "out/unwind/v1/common_pb2.py", STUBS / "unwind/v1/common_pb2.py", shallow=False)


def _declarations(text: str):
    """(line number, declaration, previous non-blank line) for every message, enum, field, value, rpc, service."""
    lines = text.splitlines()
    decl = re.compile(r"^\s*(message|enum|service|rpc|oneof)\s+\w+"
                      r"|^\s*(repeated\s+|optional\s+|map<[^>]+>\s+)?[\w.]+\s+\w+\s*=\s*\d+;|^\s*\w+\s*=\s*\d+;")
    for i, line in enumerate(lines):
        if decl.match(line):
            j = i - 1
            while j >= 0 and not lines[j].strip():
                j -= 1
            yield i + 1, line.strip(), lines[j].strip() if j >= 0 else ""


def test_every_declaration_is_commented():
    assert len(PROTOS) == 6
    missing = []
    for p in PROTOS:
        text = p.read_text()
        assert re.search(r"^package unwind\.v1;$", text, re.M), p.name
        for n, line, prev in _declarations(text):
            if not prev.startswith("//"):
                missing.append(f"{p.name}:{n}: {line}")
    assert not missing, "uncommented declarations:\n" + "\n".join(missing)


def test_every_enum_starts_with_unspecified_zero():
    for p in PROTOS:
        for name, body in re.findall(r"enum (\w+) \{(.*?)\}", p.read_text(), re.S):
            values = re.findall(r"^\s*(\w+)\s*=\s*(\d+);", body, re.M)
            first, number = values[0]
            assert first.endswith("_UNSPECIFIED") and number == "0", (p.name, name, values[0])
            assert first.replace("_", "").startswith(name.upper()), (p.name, name, first)


def test_the_services_and_their_rpcs_are_there():
    from unwind_services._proto.unwind.v1 import jobs_pb2, segmentation_pb2, skeleton_pb2, volume_pb2, warp_pb2

    def rpcs(module, service):
        return {m.name for m in module.DESCRIPTOR.services_by_name[service].methods}

    assert rpcs(volume_pb2, "VolumeService") == {"Upload", "Register", "List", "Info", "Download"}
    assert rpcs(segmentation_pb2, "SegmentationService") == {"Segment", "Simplify", "Info", "Select"}
    assert rpcs(skeleton_pb2, "SkeletonService") == {"SuggestEnds", "EstimateDeformation"}
    assert rpcs(warp_pb2, "WarpService") == {"Straighten", "Bend", "Measure", "Average", "MapPoints",
                                             "MapPointsStream"}
    assert rpcs(jobs_pb2, "JobService") >= {"Submit", "Get", "Watch", "Cancel", "List"}
    upload = volume_pb2.DESCRIPTOR.services_by_name["VolumeService"].methods_by_name["Upload"]
    watch = jobs_pb2.DESCRIPTOR.services_by_name["JobService"].methods_by_name["Watch"]
    assert upload.client_streaming and not upload.server_streaming
    assert watch.server_streaming and not watch.client_streaming
    stream = warp_pb2.DESCRIPTOR.services_by_name["WarpService"].methods_by_name["MapPointsStream"]
    assert stream.client_streaming and stream.server_streaming
