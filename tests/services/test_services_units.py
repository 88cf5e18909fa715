"""Pieces of the server tested alone: status mapping, path confinement, tokens, the interceptor on a real channel."""

from __future__ import annotations

import os
from concurrent import futures
from datetime import UTC, datetime, timedelta

import grpc
import pytest

from napari_unwind.errors import InvalidInputError, OutputError, SeriesSelectionError, UnknownFormatError, UnwindError
from unwind_services import errors as E
from unwind_services.auth import TokenAuth, add_token, hash_token, read_tokens
from unwind_services.paths import DataRoot, check_file_name

C = grpc.StatusCode


@pytest.mark.parametrize("exc, code", [
    (InvalidInputError("x"), C.INVALID_ARGUMENT),
    (UnknownFormatError("x"), C.INVALID_ARGUMENT),
    (SeriesSelectionError("x", {}), C.INVALID_ARGUMENT),
    (E.NotFoundError("x"), C.NOT_FOUND),
    (FileNotFoundError("x"), C.NOT_FOUND),
    (E.PermissionDeniedError("x"), C.PERMISSION_DENIED),
    (PermissionError("x"), C.PERMISSION_DENIED),
    (E.LimitError("x"), C.RESOURCE_EXHAUSTED),
    (MemoryError(), C.RESOURCE_EXHAUSTED),
    (OutputError("x"), C.FAILED_PRECONDITION),
    (E.StateError("x"), C.FAILED_PRECONDITION),
    (UnwindError("x"), C.FAILED_PRECONDITION),
    (E.CancelledError("x"), C.CANCELLED),
    (E.DeadlineError("x"), C.DEADLINE_EXCEEDED),
    (E.ShuttingDownError("x"), C.UNAVAILABLE),
    (E.AuthError("x"), C.UNAUTHENTICATED),
    (OSError(28, "No space left on device"), C.RESOURCE_EXHAUSTED),
])
def test_each_domain_error_has_its_status_code(exc, code):
    got, message = E.status_for(exc)
    assert got == code and message


@pytest.mark.parametrize("exc", [RuntimeError("secret /srv/x"), KeyError("k"), ZeroDivisionError(), OSError(5, "io")])
def test_anything_else_is_internal_without_its_message(exc):
    assert E.status_for(exc) == (C.INTERNAL, None)


# ------------------------------------------------------------------------------------------------------------------
def test_paths_stay_inside_the_data_root(tmp_path):
    root = DataRoot(tmp_path / "data")
    (root.root / "scans").mkdir()
    (root.root / "scans" / "a.tif").write_bytes(b"x")
    outside = tmp_path / "secret"
    outside.mkdir()
    os.symlink(outside, root.root / "scans" / "escape")
    os.symlink(root.root / "scans" / "a.tif", root.root / "scans" / "inside-link.tif")
    assert root.resolve_client_path("scans/a.tif") == root.root / "scans" / "a.tif"
    assert root.resolve_client_path("scans/inside-link.tif") == root.root / "scans" / "a.tif"
    for bad, why in (("../secret", "'..' is not allowed"), ("scans/../../secret", "'..' is not allowed"),
                     ("/etc/passwd", "absolute paths are not allowed"), ("C:\\x", "absolute paths are not allowed"),
                     ("scans/escape", "outside the server's data root"),
                     ("scans/escape/f.tif", "outside the server's data root"),
                     (".unwind/unwind.sqlite", "server's own folder"), (".unwind", "server's own folder")):
        with pytest.raises(E.PermissionDeniedError, match=why):
            root.resolve_client_path(bad)
    for bad in ("", " ", "a\x00b"):
        with pytest.raises(InvalidInputError, match="give a path relative to the server's data root"):
            root.resolve_client_path(bad)
    assert root.scrub(f"{root.root}/scans/a.tif is broken") == "scans/a.tif is broken"


@pytest.mark.parametrize("name", ["../x.zarr", "a/b.zarr", ".hidden.zarr", "", "x" * 200, "a\\b.tif"])
def test_output_names_are_plain_file_names(name):
    with pytest.raises(InvalidInputError, match="must be a plain file name"):
        check_file_name(name)


def test_tokens_are_stored_hashed_and_checked(tmp_path):
    path = tmp_path / "tokens"
    alice = add_token(path, "alice")
    short = add_token(path, "bob", days=1)
    text = path.read_text()
    assert alice not in text and short not in text and hash_token(alice) in text
    assert oct(path.stat().st_mode & 0o777) == "0o600"
    past = (datetime.now(UTC) - timedelta(days=1)).strftime("%Y-%m-%dT%H:%M:%SZ")
    with open(path, "a") as f:
        f.write(f"carol {hash_token('old-token')} expires={past}\n")
    auth = TokenAuth(path)
    assert auth.user_for(f"Bearer {alice}") == "alice"
    assert auth.user_for(f"bearer {short}") == "bob"
    for bad, words in ((None, "needs a token"), ("Bearer nope", "unknown token"), (alice, "Bearer"),
                       ("Bearer old-token", "expired")):
        with pytest.raises(E.AuthError, match=words):
            auth.user_for(bad)
    # a token added while the server runs is seen without a restart
    os.utime(path, ns=(0, 0))
    late = add_token(path, "dave")
    assert auth.user_for(f"Bearer {late}") == "dave"
    assert TokenAuth(None).user_for(None) == "local"


def test_a_malformed_tokens_file_is_refused_with_its_line(tmp_path):
    path = tmp_path / "tokens"
    path.write_text("alice not-a-hash\n")
    with pytest.raises(InvalidInputError, match="line 1"):
        read_tokens(path)


# ------------------------------------------------------------------------------------------------------------------
def test_a_bug_reaches_the_client_as_internal_without_traceback(tmp_path, caplog):
    """A servicer raising an unexpected exception: INTERNAL, a generic message; the traceback only in the log."""
    from unwind_services._proto.unwind.v1 import jobs_pb2, jobs_pb2_grpc
    from unwind_services.interceptor import ServiceInterceptor

    class Broken(jobs_pb2_grpc.JobServiceServicer):
        def Get(self, request, context):
            raise RuntimeError(f"secret detail at {tmp_path}/x.py")

        def Watch(self, request, context):
            yield jobs_pb2.JobEvent()
            raise ValueError("stream bug")

        def Cancel(self, request, context):
            raise InvalidInputError(f"{tmp_path}/data/scans/a.tif is not a scan")

    root = DataRoot(tmp_path / "data")
    server = grpc.server(futures.ThreadPoolExecutor(4), interceptors=[ServiceInterceptor(TokenAuth(None), root)])
    jobs_pb2_grpc.add_JobServiceServicer_to_server(Broken(), server)
    port = server.add_insecure_port("127.0.0.1:0")
    server.start()
    try:
        with grpc.insecure_channel(f"127.0.0.1:{port}") as ch:
            stub = jobs_pb2_grpc.JobServiceStub(ch)
            with pytest.raises(grpc.RpcError) as info:
                stub.Get(jobs_pb2.JobRef(job_id="x"), timeout=5)
            assert info.value.code() == C.INTERNAL
            details = info.value.details()
            assert "secret" not in details and "Traceback" not in details and "reference" in details
            with pytest.raises(grpc.RpcError) as info:
                list(stub.Watch(jobs_pb2.WatchRequest(job_id="x"), timeout=5))
            assert info.value.code() == C.INTERNAL and "stream bug" not in info.value.details()
            with pytest.raises(grpc.RpcError) as info:
                stub.Cancel(jobs_pb2.JobRef(job_id="x"), timeout=5)
            assert info.value.code() == C.INVALID_ARGUMENT
            assert info.value.details() == "scans/a.tif is not a scan"  # the core's message, no server path
            # a message that does not parse
            call = ch.unary_unary("/unwind.v1.JobService/Get", request_serializer=lambda b: b,
                                  response_deserializer=lambda b: b)
            with pytest.raises(grpc.RpcError) as info:
                call(b"\xff\xff\xff\xff", timeout=5)
            assert info.value.code() == C.INVALID_ARGUMENT and "malformed" in info.value.details()
    finally:
        server.stop(0)
    assert "secret detail" in caplog.text and "Traceback" in caplog.text
