"""Pieces of the server tested alone: status mapping, path confinement, tokens, the interceptor on a real channel."""

from __future__ import annotations

import os
import re
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


def test_data_root_layout_and_round_trips(tmp_path):
    """The layout of the module's docstring, written out by hand: a root whose parents do not exist yet, the
    private folder 0700, users under .unwind/users/; absolute() inverts relative() inside the root and refuses a
    path leading out of it."""
    root = DataRoot(tmp_path / "a" / "b" / "data")
    assert root.root == (tmp_path / "a" / "b" / "data").resolve()
    assert oct(os.stat(root.private).st_mode & 0o777) == "0o700"
    assert root.user_dir("alice") == root.root / ".unwind" / "users" / "alice"
    assert root.user_dir("alice").is_dir() and root.tmp == root.root / ".unwind" / "tmp"
    assert root.database == root.root / ".unwind" / "unwind.sqlite"
    (root.root / "scans").mkdir()
    f = root.root / "scans" / "a.tif"
    f.write_bytes(b"x")
    assert root.relative(f) == os.path.join("scans", "a.tif")
    assert root.absolute("scans/a.tif") == f
    with pytest.raises(E.PermissionDeniedError, match="leads outside the server's data root"):
        root.absolute("../elsewhere")


def test_client_paths_with_backslashes_and_the_full_refusals(tmp_path):
    """A Windows client's ``scans\\a.tif`` is the same file as ``scans/a.tif``; ``..\\x`` is refused like ``../x``;
    the refusals say what to give instead."""
    root = DataRoot(tmp_path / "data")
    (root.root / "scans").mkdir()
    (root.root / "scans" / "a.tif").write_bytes(b"x")
    assert root.resolve_client_path("scans\\a.tif") == root.root / "scans" / "a.tif"
    with pytest.raises(E.PermissionDeniedError, match=r"^'\.\.' is not allowed in paths, got '\.\.\\\\x'; give a "
                                                      r"path inside the server's data root$"):
        root.resolve_client_path("..\\x")
    with pytest.raises(E.PermissionDeniedError, match=r"^absolute paths are not allowed, got '/etc'; give a path "
                                                      r"relative to the server's data root$"):
        root.resolve_client_path("/etc")


@pytest.mark.parametrize("name", ["fish.zarr", "a_b-c.tif", "s_{:04d}.png", "x+y:1.nrrd", "_x", "x" * 128])
def test_plain_file_names_are_accepted(name):
    assert check_file_name(name) == name


@pytest.mark.parametrize("name", ["x" * 129, None, 5, "a..b"])
def test_long_or_non_text_names_are_refused(name):
    # 1 + 127 characters at most (the pattern); a name that is not text is refused, not a TypeError
    with pytest.raises(InvalidInputError, match="must be a plain file name"):
        check_file_name(name)


@pytest.mark.parametrize("user, ok", [("alice", True), ("a.b-c_d", True), ("7" + "x" * 63, True),
                                      ("7" + "x" * 64, False), ("-bob", False), ("", False), ("a b", False)])
def test_user_names(user, ok):
    from unwind_services.auth import check_user

    if ok:
        assert check_user(user) == user
    else:
        with pytest.raises(InvalidInputError, match=r"^a user name is 1-64 letters, digits, '_', '\.' or '-' "
                                                    r"\(starting with a letter or digit\), got "):
            check_user(user)


def test_tokens_file_lines_are_checked_field_by_field(tmp_path):
    """Each malformed line is refused naming the file and its line number; a hash of the right prefix but the wrong
    length, or the right length but another prefix, is malformed; an expiry without a zone is UTC."""
    path = tmp_path / "tokens"
    good = hash_token("a")  # "sha256:" + 64 hex digits: 71 characters
    assert len(good) == 71
    for line, words in ((f"bob {good[:-1]}", "expected 'USER sha256:<64 hex digits> [expires=TIME]'"),
                        (f"bob md5:{good[4:]}", "expected 'USER sha256:"),
                        (f"bob {good} until=2027-01-01", "the third field must be expires=TIME"),
                        (f"bob {good} expires=tomorrow", "expires= must be an ISO 8601 time such as "
                                                         "2027-01-31T00:00:00Z, got 'tomorrow'")):
        path.write_text(f"# comment\n{line}\n")
        with pytest.raises(InvalidInputError, match="^" + re.escape(f"{path} line 2: {words}")):
            read_tokens(path)
    path.write_text(f"carol {good} expires=2000-01-01T00:00:00  # naive: UTC\n")
    assert read_tokens(path) == {good: ("carol", datetime(2000, 1, 1, tzinfo=UTC))}
    with pytest.raises(E.AuthError, match=r"^the token of user 'carol' expired on 2000-01-01T00:00:00\+00:00; ask "
                                          r"the server's administrator for a new one$"):
        TokenAuth(path).user_for("Bearer a")


def test_add_token_keeps_a_last_line_without_newline_and_writes_the_header(tmp_path):
    """An admin's tokens file whose last line has no newline keeps that line when a token is added; a new file
    starts with the format comment."""
    path = tmp_path / "tokens"
    path.write_text(f"alice {hash_token('a')}")  # no newline at the end
    bob = add_token(path, "bob")
    auth = TokenAuth(path)
    assert auth.user_for("Bearer a") == "alice" and auth.user_for(f"Bearer {bob}") == "bob"
    fresh = tmp_path / "fresh"
    add_token(fresh, "carol")
    assert fresh.read_text().splitlines()[0] == "# napari-unwind tokens: USER sha256:<hash> [expires=TIME]"


def test_the_bearer_value_may_have_extra_spaces_and_the_missing_token_error_says_how(tmp_path):
    path = tmp_path / "tokens"
    path.write_text(f"alice {hash_token('a')}\n")
    auth = TokenAuth(path)
    assert auth.user_for("Bearer  a ") == "alice"  # the token is what follows the first space, stripped
    with pytest.raises(E.AuthError) as info:
        auth.user_for("")
    assert str(info.value) == ("this server needs a token: pass it as 'authorization: Bearer <token>' "
                               "(Client(token=...); on the command line --token=TOKEN, --token-file PATH, "
                               "$UNWIND_TOKEN or $UNWIND_TOKEN_FILE)")


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
