"""A fuzz of every field of every request message (issue 22 item 4): random fields of random methods set to
random awkward values (lengths, NaN, infinities, NUL, huge numbers, empty and huge repeated fields), with a fixed
seed, through a real in-process server. Never INTERNAL or UNKNOWN, never a job (no object id of the fuzz exists,
given to a job so nothing passes Submit; the others get an existing volume's id half the time, so the values
reach the code behind the lookups), never a long message, and the server still serves afterwards."""

from __future__ import annotations

import logging
import math
import random

import pytest
from _bounds import BAD, call, methods, small_server
from google.protobuf import message_factory
from google.protobuf.descriptor import FieldDescriptor as F

from napari_unwind.client import Client

SEED, CALLS = 20261203, 2000
INTS = [0, 1, -1, 2, 3, 100, 101, 255, 4096, 4097, 10_000, 10_001, 2**31 - 1, -2**31]
INT64S = INTS + [2**53, 2**63 - 1, -2**63]
DOUBLES = [0.0, -0.0, 1.0, -1.0, 0.5, 1e-300, 5e-324, 1e9, 1e12, 1.7e308, -1.7e308, math.nan, math.inf, -math.inf]
STRINGS = ["", "a", "\x00", "a\x00b", ".", "..", "/", "../x", "/etc/passwd", "scans", "scans/small.tif",
           "x" * 255, "x" * 256, "é" * 200, "d/" * 2100, ("d" * 255 + "/") * 17, ".tif", ".zarr", "raw",
           "tif\x00", "\ud7ff" * 50, "vol-000000000000", "ses-000000000000", "job-000000000000"]


#: Methods that create a job: the fuzz gives them no existing id (else a valid draw would start real work).
JOB_METHODS = {"Submit", "Resubmit", "Segment", "Select", "EstimateDeformation", "Straighten", "Bend"}


def _value(rng: random.Random, fd, real: list[str]):
    if fd.type == F.TYPE_STRING:
        if real and fd.name.endswith("_id") and rng.random() < 0.8:
            return rng.choice(real)
        return rng.choice(STRINGS + ["".join(chr(rng.randrange(1, 0xD7FF)) for _ in range(rng.randrange(40)))])
    if fd.type == F.TYPE_BYTES:
        return rng.choice([b"", b"\x00" * rng.randrange(100)])
    if fd.type in (F.TYPE_DOUBLE, F.TYPE_FLOAT):
        return rng.choice(DOUBLES + [rng.uniform(-1e6, 1e6)])
    if fd.type == F.TYPE_INT64:
        return rng.choice(INT64S + [rng.randrange(-2**63, 2**63)])
    if fd.type == F.TYPE_INT32:
        return rng.choice(INTS + [rng.randrange(-2**31, 2**31)])
    if fd.type == F.TYPE_BOOL:
        return rng.random() < 0.5
    if fd.type == F.TYPE_ENUM:
        return rng.choice(list(fd.enum_type.values_by_number) + [99, -1])
    raise AssertionError(fd.type)


def _fill(rng: random.Random, msg, real: list[str], depth: int = 0) -> None:
    """Set a random subset of the message's fields (a oneof: one of its members) to random values."""
    fields = list(msg.DESCRIPTOR.fields)
    for fd in rng.sample(fields, k=rng.randint(1, min(len(fields), 2))):
        if fd.is_repeated:
            n = rng.choice([0, 1, 2, 3, 4, 1001, 10_001])
            target = getattr(msg, fd.name)
            if fd.type == F.TYPE_MESSAGE:
                for _ in range(min(n, 1001) if depth else n):
                    item = target.add()
                    if depth < 2 and rng.random() < 0.3:
                        _fill(rng, item, real, depth + 1)
            else:
                one = _value(rng, fd, real)
                target.extend([one if rng.random() < 0.7 else _value(rng, fd, real) for _ in range(n)])
        elif fd.type == F.TYPE_MESSAGE:
            sub = getattr(msg, fd.name)
            sub.SetInParent()
            if depth < 3:
                _fill(rng, sub, real, depth + 1)
        else:
            setattr(msg, fd.name, _value(rng, fd, real))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from small_server(tmp_path_factory.mktemp("fuzz"))


def test_a_seeded_fuzz_of_every_request_never_gets_internal(server, caplog):
    from unwind_services.auth import LOCAL_USER

    srv, channel = server
    rng = random.Random(SEED)
    all_methods = methods()
    with Client(f"127.0.0.1:{srv.port}", progress=False) as c:  # an existing volume, for the calls that make no job
        real = [c.register("scans/small.tif").volume_id]
    codes: dict[str, int] = {}
    seen_fields: set[str] = set()
    with caplog.at_level(logging.INFO, logger="unwind_services"):
        for i in range(CALLS):
            svc, method = rng.choice(all_methods)
            msg = message_factory.GetMessageClass(method.input_type)()
            if real and method.name not in JOB_METHODS:  # the volume's id set, so the fuzzed values reach past it
                for fd in msg.DESCRIPTOR.fields:
                    if fd.name.endswith("volume_id") and not fd.is_repeated:
                        setattr(msg, fd.name, real[0])
            _fill(rng, msg, [] if method.name in JOB_METHODS else real)
            for fd, _ in msg.ListFields():
                seen_fields.add(f"{method.input_type.name}.{fd.name}")
            code, details = call(channel, svc, method, msg)
            assert code not in BAD, (i, method.full_name, str(msg)[:2000], code, details)
            assert len(details) <= 1000, (i, method.full_name, len(details))
            codes[code.name if code else "OK"] = codes.get(code.name if code else "OK", 0) + 1
    assert srv.store.list_jobs(LOCAL_USER, 0, 1000) == [], "a fuzzed Submit created a job"
    assert codes.get("INVALID_ARGUMENT", 0) > CALLS // 6, codes  # the fuzz does reach the bounds
    assert len(seen_fields) > 40, sorted(seen_fields)
    for r in caplog.records:
        if r.name.startswith("unwind_services") and r.levelno < logging.ERROR:
            assert len(r.getMessage()) <= 500, r.getMessage()[:600]
    with Client(f"127.0.0.1:{srv.port}", progress=False) as c:  # still serving
        assert list(c.register("scans/small.tif").shape) == [6, 5, 4]
