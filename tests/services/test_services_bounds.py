"""Every field of every request has bounds checked where it arrives (issue 22 items 2a and 4).

The bounds are read from the .proto comments (the contract, "Bounds: ..."), not from the server's table; every
field reachable from a request must document one, and for each the test sends values just outside (and far
outside: the type's extremes, NaN, infinities, NUL, too long, too many items) through a real in-process server:
each is INVALID_ARGUMENT naming the field, and a job's at Submit (no job is ever created). The values at the
bounds are not refused as out of bounds. Then the seven cases the issue names, one test each, and the log."""

from __future__ import annotations

import errno
import logging
import math
import sqlite3

import grpc
import pytest
from _bounds import BAD, build, call, documented_bounds, parse, request_fields, small_server
from google.protobuf.descriptor import FieldDescriptor as F

from napari_unwind.client import Client
from unwind_services._proto.unwind.v1 import jobs_pb2, jobs_pb2_grpc, volume_pb2, volume_pb2_grpc, warp_pb2

C = grpc.StatusCode
INT_RANGE = {F.TYPE_INT32: (-2**31, 2**31 - 1), F.TYPE_INT64: (-2**63, 2**63 - 1)}
FIELDS = request_fields()
DOCS = documented_bounds()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    yield from small_server(tmp_path_factory.mktemp("bounds"))


def _jobs(srv) -> list:
    from unwind_services.auth import LOCAL_USER

    return srv.store.list_jobs(LOCAL_USER, 0, 1000)


def _where(method, path) -> str:
    parts = [method.input_type.name]
    for fd in path[:-1]:
        parts.append(fd.name + ("[0]" if fd.is_repeated else ""))
    return ".".join(parts + [path[-1].name])


def _cast(fd, v):
    return int(v) if fd.type in INT_RANGE else float(v)


def _item(fd, doc):
    """An item within its bound (for a repeated field of scalars)."""
    if doc is None or doc.kind != "range":
        return _cast(fd, 0)
    return _cast(fd, doc.lo if doc.lo > 0 else min(doc.hi, max(doc.lo, 1.0)))


def _scalar_outside(fd, doc) -> list:
    if doc.kind == "enum":
        return [999]
    if doc.kind == "text":
        vals = ["a" * (doc.max_bytes + 1), "a\x00b", "\x00"]
        if doc.path:
            vals += ["a/" + "b" * 256, "a/" * (doc.max_bytes // 2 + 1)]
        return vals
    if doc.kind == "finite":
        return [math.nan, math.inf, -math.inf]
    if doc.kind != "range":
        return []
    if fd.type in INT_RANGE:
        tlo, thi = INT_RANGE[fd.type]
        return sorted({v for v in (int(doc.hi) + 1, int(doc.lo) - 1, thi, tlo) if tlo <= v <= thi
                       and not doc.lo <= v <= doc.hi})
    return [doc.hi * 2 + 1, doc.lo - 1 if doc.lo >= 0 else doc.lo * 2 - 1, math.nan, math.inf, -math.inf]


def outside(fd, doc) -> list:
    """Values outside the documented bound (a count for a repeated field of messages)."""
    if not fd.is_repeated:
        return _scalar_outside(fd, doc)
    vals = []
    n = max(doc.counts) + 1 if doc.counts else doc.max_items + 1
    vals.append(n if fd.type == F.TYPE_MESSAGE else [_item(fd, doc.each)] * n)
    if doc.counts and 1 not in doc.counts:
        vals.append([_item(fd, doc.each)])
    if doc.each is not None:
        k = max(doc.counts) if doc.counts else 1
        vals += [[bad] + [_item(fd, doc.each)] * (k - 1) for bad in _scalar_outside(fd, doc.each)]
    return vals


def inside(fd, doc) -> list:
    """Values at the documented bound (not refused as out of bounds)."""
    if fd.is_repeated:
        n = max(doc.counts) if doc.counts else doc.max_items
        if fd.type == F.TYPE_MESSAGE:
            return [n]
        return [[_cast(fd, doc.each.hi if doc.each else 0)] * n] + ([[_cast(fd, doc.each.lo)] * n] if doc.each else [])
    if doc.kind == "range":
        return [_cast(fd, doc.hi), _cast(fd, doc.lo)]
    if doc.kind == "finite":
        return [1e300, -1e300]
    if doc.kind == "text":
        if doc.path:
            return [("d" * 200 + "/") * (doc.max_bytes // 201) + "x", "f" * 255]
        return ["a" * doc.max_bytes]
    return []


def test_every_request_field_documents_its_bounds_and_the_server_has_one():
    from unwind_services.convert import bounds

    assert len(FIELDS) > 90
    missing = sorted(k for k in FIELDS if k not in DOCS)
    assert not missing, f"fields without a '// Bounds:' comment in the protos: {missing}"
    unread = [k for k in FIELDS if parse(DOCS[k]) is None]
    assert not unread
    table = bounds()
    assert sorted(k for k in FIELDS if k not in table) == [], "fields without a bound in convert.bounds()"


@pytest.mark.parametrize("key", sorted(FIELDS))
def test_out_of_bounds_values_are_invalid_argument_naming_the_field(server, key):
    srv, channel = server
    (svc, method), path = FIELDS[key]
    fd, doc = path[-1], parse(DOCS[key])
    where = _where(method, path)
    before = len(_jobs(srv))
    for value in outside(fd, doc):
        code, details = call(channel, svc, method, build(method, path, value))
        shown = value if not isinstance(value, (str, list)) or len(value) < 20 else f"{type(value).__name__} " \
                                                                                   f"of {len(value)}"
        assert code == C.INVALID_ARGUMENT, (key, shown, code, details)
        assert where in details, (key, shown, details)
        assert len(details) < 1000
    for value in inside(fd, doc):
        code, details = call(channel, svc, method, build(method, path, value))
        assert code not in BAD, (key, code, details)
        assert not (code == C.INVALID_ARGUMENT and where in details), (key, "refused at its bound", details)
    assert len(_jobs(srv)) == before == 0, "a job was created"


# ------------------------------------------------------------------------------------------------------------------
# the seven cases of the issue
# ------------------------------------------------------------------------------------------------------------------
def _register(channel, path, name=""):
    return volume_pb2_grpc.VolumeServiceStub(channel).Register(volume_pb2.RegisterRequest(path=path, name=name))


@pytest.mark.parametrize("path, code", [
    ("scans/" + "x" * 300 + ".tif", C.INVALID_ARGUMENT),           # a name over 255 bytes
    ("scans/" + "d/" * 3000 + "x.tif", C.INVALID_ARGUMENT),         # deeper than PATH_MAX
    ("scans/" + ("d" * 250 + "/") * 17 + "x.tif", C.INVALID_ARGUMENT),
    (("d" * 250 + "/") * 16 + "x" * 80, C.INVALID_ARGUMENT),         # 4096 bytes: past PATH_MAX with the root
    ("scans/" + "d/" * 1000 + "x.tif", C.NOT_FOUND),                 # deep but within the bounds
])
def test_long_and_deep_register_paths_are_refused_not_internal(server, path, code):
    _, channel = server
    with pytest.raises(grpc.RpcError) as err:
        _register(channel, path)
    assert err.value.code() == code, err.value.details()
    assert len(err.value.details()) < 1000


@pytest.mark.parametrize("name", ["n" * 300, "a\x00b"])
def test_long_and_nul_names_are_invalid_argument(server, name):
    _, channel = server
    with pytest.raises(grpc.RpcError) as err:
        _register(channel, "scans/small.tif", name=name)
    assert err.value.code() == C.INVALID_ARGUMENT


def _volume(channel) -> str:
    return _register(channel, "scans/small.tif", "small.tif").volume_id


def _submit(channel, **spec):
    return jobs_pb2_grpc.JobServiceStub(channel).Submit(jobs_pb2.SubmitRequest(**spec))


def _straighten(**options):
    return lambda vid: dict(straighten=warp_pb2.StraightenRequest(volume_id=vid, session_id="ses-000000000000",
                                                                  options=warp_pb2.ExportOptions(**options)))


def _estimate(**options):
    from unwind_services._proto.unwind.v1 import skeleton_pb2

    return lambda vid: dict(estimate_deformation=skeleton_pb2.EstimateDeformationRequest(
        mask_volume_id=vid, options=skeleton_pb2.SkeletonOptions(**options)))


def _segment(**spec):
    from unwind_services._proto.unwind.v1 import segmentation_pb2

    return lambda vid: dict(segment=segmentation_pb2.SegmentRequest(volume_id=vid), **spec)


@pytest.mark.parametrize("spec, field", [
    (_segment(timeout_seconds=math.nan), "timeout_seconds"),
    (_segment(timeout_seconds=math.inf), "timeout_seconds"),
    (_segment(timeout_seconds=-1.0), "timeout_seconds"),
    (_straighten(chunks=[0, 0, 0]), "chunks"),
    (_straighten(chunks=[64, 64]), "chunks"),
    (_straighten(output_name="o" * 300 + ".zarr"), "output_name"),
    (_straighten(output_name="a\x00.zarr"), "output_name"),
    (_straighten(order=2, has_order=True), "order"),                        # within 0..3, the core refuses 2
    (_estimate(levels=1), "n_levels"),                                       # within 0..10000, the core: >= 2
    (_estimate(half_extent=[0.0, 0.0]), "half_extent"),                     # within 0..1e9, the core: positive
    (lambda vid: dict(bend=warp_pb2.BendRequest(volume_id=vid, session_id="ses-000000000000", order=2,
                                                has_order=True)), "order"),
    (lambda vid: dict(pipeline=jobs_pb2.PipelineRequest(volume_id=vid)), "exactly one of"),
])
def test_bad_job_values_are_refused_at_submit(server, spec, field):
    """With a real volume (and a session id that does not exist: NOT_FOUND would come after the bounds). The last
    cases are within the wire's bounds but refused by the core's options, which Submit builds as the job would."""
    srv, channel = server
    with pytest.raises(grpc.RpcError) as err:
        _submit(channel, **spec(_volume(channel)))
    assert err.value.code() == C.INVALID_ARGUMENT, err.value.details()
    assert field in err.value.details()
    assert _jobs(srv) == []


@pytest.mark.parametrize("fmt", ["ti\x00f", ".tif\x00", "x" * 300, "raw\x00", ".zarr\x00", "\x00", "nii.gz\x00",
                                 ".t\x00if"])
def test_a_download_format_with_nul_or_too_long_is_invalid_argument(server, fmt):
    _, channel = server
    vid = _volume(channel)
    stub = volume_pb2_grpc.VolumeServiceStub(channel)
    with pytest.raises(grpc.RpcError) as err:
        list(stub.Download(volume_pb2.DownloadRequest(volume_id=vid, format=fmt)))
    assert err.value.code() == C.INVALID_ARGUMENT, err.value.details()
    assert "format" in err.value.details()
    assert len(list(stub.Download(volume_pb2.DownloadRequest(volume_id=vid, format="tif")))) >= 2  # still fine


def _sqlite_full() -> sqlite3.OperationalError:
    """A real "database or disk is full" of SQLite: a database that may not grow past its pages."""
    db = sqlite3.connect(":memory:")
    db.execute("CREATE TABLE t (x)")
    db.execute("PRAGMA max_page_count=2")
    try:
        while True:
            db.execute("INSERT INTO t VALUES (?)", ("x" * 1000,))
    except sqlite3.OperationalError as exc:
        assert exc.sqlite_errorcode == sqlite3.SQLITE_FULL
        return exc
    finally:
        db.close()


@pytest.mark.parametrize("where", ["database", "folder"])
def test_submit_on_a_full_disk_is_resource_exhausted(server, monkeypatch, where):
    """The job table cannot grow (SQLite's own full-disk error) or the job's folder cannot be made (ENOSPC):
    RESOURCE_EXHAUSTED with a short message naming no server path, not INTERNAL or FAILED_PRECONDITION."""
    from unwind_services._proto.unwind.v1 import segmentation_pb2

    srv, channel = server
    vid = _volume(channel)
    full = _sqlite_full() if where == "database" else OSError(errno.ENOSPC, "No space left on device",
                                                              str(srv.root.root / ".unwind" / "users"))

    def fail(*args, **kwargs):
        raise full

    monkeypatch.setattr(srv.store if where == "database" else srv.catalog.root,
                        "add_job" if where == "database" else "user_dir", fail)
    with pytest.raises(grpc.RpcError) as err:
        _submit(channel, segment=segmentation_pb2.SegmentRequest(volume_id=vid))
    assert err.value.code() == C.RESOURCE_EXHAUSTED, err.value.details()
    assert "disk is full" in err.value.details() and str(srv.root.root) not in err.value.details()
    monkeypatch.undo()
    assert _jobs(srv) == []


def test_the_cores_full_disk_error_is_resource_exhausted_not_failed_precondition(tmp_path):
    """The core wraps ENOSPC in its OutputError (an UnwindError: FAILED_PRECONDITION by its class): a job that
    fills the disk fails RESOURCE_EXHAUSTED, and the message names no server path."""
    from napari_unwind.io._api import disk_full_error
    from unwind_services.errors import status_for

    def raised():
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as exc:
            err = disk_full_error(exc, tmp_path / "out.zarr")
            assert err is not None
            raise err from None

    with pytest.raises(Exception) as caught:
        raised()
    code, message = status_for(caught.value)
    assert code == C.RESOURCE_EXHAUSTED
    assert str(tmp_path) not in message


def test_a_60_mib_path_leaves_one_short_line_in_the_log(server, caplog):
    _, channel = server
    huge = "scans/" + "p" * (60 * 2**20)
    with caplog.at_level(logging.DEBUG):
        with pytest.raises(grpc.RpcError) as err:
            _register(channel, huge)
        with pytest.raises(grpc.RpcError):
            _register(channel, "scans/" + "q" * 300 + "\x00")
    assert err.value.code() == C.INVALID_ARGUMENT
    assert len(err.value.details()) < 1000
    records = [r for r in caplog.records if r.name.startswith("unwind_services")]
    assert len(records) == 2, [r.getMessage()[:200] for r in records]
    for r in records:
        text = r.getMessage()
        assert len(text) <= 500 and "\n" not in text and "Traceback" not in text, text[:600]
    total = sum(len(r.getMessage()) + len(r.exc_text or "") for r in caplog.records)
    assert total < 10_000


def test_an_internal_error_logs_a_bounded_traceback(tmp_path, caplog):
    """A bug (not the client's input) keeps its traceback in the log, cut to a bounded size even when the
    exception holds a huge value; the caller gets the generic message."""
    from unwind_services import interceptor
    from unwind_services.auth import TokenAuth
    from unwind_services.paths import DataRoot

    class Context:
        def abort(self, code, message):
            self.code, self.message = code, message
            raise RuntimeError("aborted")

    icpt, context = interceptor.ServiceInterceptor(TokenAuth(None), DataRoot(tmp_path)), Context()
    with caplog.at_level(logging.DEBUG):
        try:
            raise KeyError("k" * (10 * 2**20))
        except KeyError as exc:
            with pytest.raises(RuntimeError, match="aborted"):
                icpt._abort(exc, context, "/unwind.v1.VolumeService/" + "M" * 10_000)
    assert context.code == C.INTERNAL and "reference" in context.message and "kkk" not in context.message
    text = "\n".join(r.getMessage() for r in caplog.records if r.name.startswith("unwind_services"))
    assert "KeyError" in text and len(text) <= interceptor.MAX_TRACEBACK + 1000, len(text)
    assert max(len(line) for line in text.splitlines()) <= interceptor.MAX_LOG_LINE


def test_a_long_refusal_is_one_short_line_in_the_log_and_to_the_caller(tmp_path, caplog):
    """Whatever the message of a refusal (a core error quoting a huge value), the caller gets at most
    MAX_MESSAGE characters and the log one line of at most MAX_LOG_LINE."""
    from napari_unwind.errors import InvalidInputError
    from unwind_services import interceptor
    from unwind_services.auth import TokenAuth
    from unwind_services.paths import DataRoot

    class Context:
        def abort(self, code, message):
            self.code, self.message = code, message
            raise RuntimeError("aborted")

    icpt, context = interceptor.ServiceInterceptor(TokenAuth(None), DataRoot(tmp_path)), Context()
    with caplog.at_level(logging.DEBUG), pytest.raises(RuntimeError, match="aborted"):
        icpt._abort(InvalidInputError("bad value " + "v" * 2**20), context, "/unwind.v1.X/" + "M" * 2**20)
    assert context.code == C.INVALID_ARGUMENT and context.message.startswith("bad value vvv")
    assert len(context.message) <= interceptor.MAX_MESSAGE
    lines = [r.getMessage() for r in caplog.records if r.name.startswith("unwind_services")]
    assert len(lines) == 1 and len(lines[0]) <= interceptor.MAX_LOG_LINE and "\n" not in lines[0]


def test_no_job_was_created_by_any_refused_submit(server):
    srv, _ = server
    assert _jobs(srv) == []
    with Client(f"127.0.0.1:{srv.port}", progress=False) as c:
        assert c.jobs() == []


@pytest.mark.parametrize("kind, name, value", [
    ("SkeletonOptions", "n_levels", 2**31 - 1), ("SkeletonOptions", "smoothing_iterations", 2**31 - 1),
    ("SkeletonOptions", "cage_radius", 1e300), ("SkeletonOptions", "tolerance", 1e300),
    ("SkeletonOptions", "snap_tolerance", 1e300), ("SkeletonOptions", "half_extent", (1e300, 1.0)),
    ("SkeletonOptions", "cage_margin", 1e300), ("SegmentOptions", "level", 2**31 - 1),
    ("SegmentOptions", "smooth", 1e300), ("SegmentOptions", "min_elongation", 1e300),
    ("ExportOptions", "pad", 2**31 - 1), ("ExportOptions", "chunks", (0, 0, 0)),
    ("ExportOptions", "chunks", (2**31 - 1, 64, 64)), ("ExportOptions", "spacing", 1e300),
])
def test_the_cores_options_refuse_huge_values_on_every_face(kind, name, value):
    """The command line and the dock build the same option objects as the server: each has an upper bound."""
    from napari_unwind import pipeline
    from napari_unwind.errors import InvalidInputError

    with pytest.raises(InvalidInputError, match=name):
        getattr(pipeline, kind)(**{name: value})
