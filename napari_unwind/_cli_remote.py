"""The remote commands of ``unwind``: ``serve``, ``submit``, ``jobs`` and ``run --server``.

:func:`add_remote_commands` adds the subcommands to the ``unwind`` parser; :func:`run_remote` runs ``unwind run``
on a server. The entry is ``unwind`` (or ``python -m napari_unwind.cli``): this module imports no part of
:mod:`napari_unwind.cli` (their shared argument types live in :mod:`napari_unwind._cliargs`). Needs the ``server``
extra.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
from pathlib import Path
from typing import Any

from .errors import InvalidInputError, UnwindError

__all__ = ["add_remote_commands", "run_remote"]


def _add_client_options(p: argparse.ArgumentParser, server_required: bool = False) -> None:
    p.add_argument("--server", default=None if server_required else os.environ.get("UNWIND_SERVER", "127.0.0.1:50051"),
                   required=server_required and not os.environ.get("UNWIND_SERVER"), metavar="HOST:PORT",
                   help="the server's address (default $UNWIND_SERVER or 127.0.0.1:50051)")
    _add_token_options(p)


class _TokenFileAction(argparse.Action):
    """``--token-file PATH``: reads the token (one line) into ``token``; a bad file is a one-line argparse error."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        from ._tokenfile import read_token_file

        try:
            token = read_token_file(values)
        except InvalidInputError as exc:
            raise argparse.ArgumentError(self, str(exc)) from None
        setattr(namespace, self.dest, values)
        namespace.token = token


def _add_token_options(p: argparse.ArgumentParser) -> None:
    who = p.add_mutually_exclusive_group()
    who.add_argument("--token", default=None, metavar="TOKEN",
                     help="your token (default $UNWIND_TOKEN); --token=TOKEN takes any token, one that starts with "
                          "'-' too")
    who.add_argument("--token-file", default=None, metavar="PATH", action=_TokenFileAction,
                     help="a file holding your token alone on one line (default $UNWIND_TOKEN_FILE); keeps the "
                          "token out of the shell's history and the process list")
    p.add_argument("--tls", action="store_true", help="connect with TLS (system root certificates)")
    p.add_argument("--tls-ca", default=None, metavar="PEM", help="connect with TLS, trusting this CA certificate")
    p.add_argument("--timeout", type=float, default=60.0, help="deadline of each call, seconds (default 60)")


def _client(args: argparse.Namespace):
    from .client import Client

    server = getattr(args, "server", None) or os.environ.get("UNWIND_SERVER", "127.0.0.1:50051")
    tls: Any = getattr(args, "tls_ca", None) or bool(getattr(args, "tls", False))
    return Client(server, token=getattr(args, "token", None), tls=tls, timeout=getattr(args, "timeout", 60.0),
                  progress=not getattr(args, "quiet", False))


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return v


def _non_negative_float(text: str) -> float:
    """Seconds >= 0, finite (0: no limit where the option says so)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, got {text!r}") from None
    if not 0 <= v < float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds >= 0, got {text!r}")
    return v


def _port(text: str) -> int:
    """A TCP port, 0..65535 (0: any free port); gRPC took 99999 and listened on a port of its choosing."""
    v = _positive_int(text)
    if v > 65535:
        raise argparse.ArgumentTypeError(f"a port is a whole number in 0..65535 (0: any free port), got {text!r}")
    return v


def _days(text: str) -> float:
    """A positive, finite number of days (--expires-days inf gave a traceback)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of days > 0, got {text!r}") from None
    if not (v > 0 and v <= 36500):
        raise argparse.ArgumentTypeError(f"expected a number of days in (0, 36500], got {text!r}; leave "
                                         "--expires-days out for a token that does not expire")
    return v


# ------------------------------------------------------------------------------------------------------------------
# unwind serve
# ------------------------------------------------------------------------------------------------------------------
#: ``unwind serve`` options that are fields of ``unwind_services.catalog.Limits`` of the same name, with their
#: defaults there (the parser's default None means "not given").
_PER_USER_LIMITS = ("max_running_per_user", "max_uploads_per_user", "max_stored_bytes_per_user", "max_calls_per_user",
                    "max_call_rate_per_user", "upload_idle_seconds", "download_idle_seconds")


def cmd_serve(args: argparse.Namespace) -> int:
    from unwind_services.auth import add_token
    from unwind_services.catalog import Limits
    from unwind_services.server import ServerConfig, UnwindServer

    if args.add_token:
        if not args.tokens:
            raise InvalidInputError("--add-token USER needs --tokens FILE (where the token's hash is stored)")
        token = add_token(args.tokens, args.add_token, days=args.expires_days)
        print(f"token for {args.add_token} (shown once; its hash is in {args.tokens}):")
        print(token)
        return 0
    if not args.data_root:
        raise InvalidInputError("give the folder the server keeps its data in: --data-root DIR")
    logging.basicConfig(level=getattr(logging, args.log_level.upper(), logging.INFO),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    given = {name: getattr(args, name) for name in _PER_USER_LIMITS if getattr(args, name) is not None}
    limits = Limits(max_upload_bytes=args.max_upload_bytes, max_voxels=args.max_voxels,
                    max_message_bytes=args.max_message_bytes, max_jobs_per_user=args.max_jobs_per_user, **given)
    drain = {} if args.drain is None else {"drain_seconds": args.drain}  # default: ServerConfig's
    config = ServerConfig(data_root=Path(args.data_root), port=args.port, listen=args.listen,
                          services=args.service or (), scheduler=args.scheduler,
                          tokens=Path(args.tokens) if args.tokens else None,
                          tls_cert=Path(args.tls_cert) if args.tls_cert else None,
                          tls_key=Path(args.tls_key) if args.tls_key else None, limits=limits, workers=args.workers,
                          imports=args.imports or 0, **drain)
    UnwindServer(config).serve_forever()
    return 0


# ------------------------------------------------------------------------------------------------------------------
# unwind submit
# ------------------------------------------------------------------------------------------------------------------
def _print_job(job: Any, file=None) -> None:
    from unwind_services._proto.unwind.v1 import common_pb2 as pb

    state = pb.JobState.Name(job.state)[len("JOB_STATE_"):].lower()
    kind = pb.JobKind.Name(job.kind)[len("JOB_KIND_"):].lower()
    line = f"{job.id}  {kind:<20} {state:<10} {job.name}"
    if job.progress.stage:
        p = job.progress
        line += f"  [{p.stage} {p.done}/{p.total or '?'}]"
    if job.interrupted:
        line += "  (interrupted)"
    if job.error.code:
        line += f"  {job.error.code}: {job.error.message}"
    if job.result.volume_id:
        line += f"  -> {job.result.volume_id}"
    if job.result.HasField("verdict"):  # a skeleton or pipeline job: the pipeline's status of its specimen
        line += f"  {_status(job)}"
    print(line, file=file or sys.stdout)


def _status(job: Any) -> str:
    """``ok`` or ``partial: <the pipeline's reason>`` (the job's verdict)."""
    from .client import Client

    r = Client.specimen(job)
    return f"{r.status}: {_one_line(r.reason)}" if r.reason else r.status


def _one_line(message: str) -> str:
    return " ".join(message.split())


def _exit_of(job: Any) -> int:
    """The exit status of a finished job as the local command gives it: 0 succeeded (and, for a skeleton or
    pipeline job, ``ok``), :data:`~napari_unwind.pipeline.EXIT_PARTIAL` for a ``partial`` specimen (with its reason
    on stderr), 1 otherwise."""
    from unwind_services._proto.unwind.v1 import common_pb2 as pb

    from .client import Client
    from .pipeline import exit_status

    if job.state != pb.JOB_STATE_SUCCEEDED:
        return 1
    if job.kind not in (pb.JOB_KIND_ESTIMATE_DEFORMATION, pb.JOB_KIND_PIPELINE):
        return 0
    r = Client.specimen(job)
    if r.status != "ok":
        print(f"unwind: {r.status}: job {job.id}: {_one_line(r.reason)}", file=sys.stderr)
    return exit_status([r])


def cmd_submit(args: argparse.Namespace) -> int:
    from .client import BatchItem

    client = _client(args)
    with client:
        if args.batch:
            items = _read_batch(Path(args.batch), register=args.register)
            rows = client.run_batch(items, max_parallel=args.max_parallel, out_dir=args.out_dir,
                                    summary=args.summary, progress=not args.quiet)
            failed = [r for r in rows if r.get("state") != "succeeded"]
            partial = [r for r in rows if r.get("state") == "succeeded" and r.get("status") != "ok"]
            if not args.quiet:
                print(f"{len(rows) - len(failed) - len(partial)} of {len(rows)} specimens straightened"
                      + (f", {len(partial)} partial" if partial else "")
                      + (f"; summary: {args.summary or Path(args.out_dir) / 'summary.csv'}"
                         if args.summary or args.out_dir else ""))
            for r in failed:
                print(f"unwind: {r['name']}: {r.get('error', '')}", file=sys.stderr)
            for r in partial:  # straightened, but not to the goals: not a success (as unwind run)
                print(f"unwind: {r.get('status') or 'partial'}: {r['name']}: {r.get('reason', '')}", file=sys.stderr)
            from .pipeline import EXIT_PARTIAL

            return 1 if failed else (EXIT_PARTIAL if partial else 0)
        if not args.input:
            raise InvalidInputError("give a scan (INPUT) or a collection (--batch FILE.csv)")
        if not args.select and not args.mask:
            raise InvalidInputError("say which specimen: --select A0,A1,A2 (a point inside it) or --mask MASK")
        item = BatchItem(scan=args.input, register=args.register)
        if args.register:
            vid = client.register(args.input).volume_id
        elif args.input.startswith("vol-") and not Path(args.input).exists():
            vid = args.input
        else:
            vid = client.upload(args.input).volume_id
        mask_id = ""
        if args.mask:
            mask_id = (client.register(args.mask) if args.register else client.upload(args.mask)).volume_id
        name = args.name or (Path(item.scan).name.split(".")[0] + ".zarr")
        job = client.pipeline(vid, select=args.select, mask_volume_id=mask_id, features=args.features,
                              isovalue=args.isovalue, fill_holes=args.fill_holes, head=args.head, tail=args.tail,
                              output_name=name, order=args.order, pad=args.pad, spacing=args.spacing,
                              allow_folds=args.allow_folds, wait=args.wait, name=name)
        _print_job(job)
    return _exit_of(job) if args.wait else 0


def _read_batch(path: Path, register: bool) -> list:
    """A collection file (:func:`napari_unwind.batch.read_batch`: CSV with columns scan, select, name, or a JSON
    list of such items), checked against its schema."""
    from .batch import read_batch
    from .client import BatchItem

    return [BatchItem(**item, register=register) for item in read_batch(path)]


# ------------------------------------------------------------------------------------------------------------------
# unwind jobs
# ------------------------------------------------------------------------------------------------------------------
def cmd_jobs(args: argparse.Namespace) -> int:
    if args.action != "list" and not args.job_id:
        raise InvalidInputError(f"unwind jobs {args.action} needs a job id")
    with _client(args) as client:
        if args.action == "list":
            for job in client.jobs(limit=args.limit):
                _print_job(job)
        elif args.action == "get":
            job = client.job(args.job_id)
            if args.json:
                from google.protobuf.json_format import MessageToDict

                print(json.dumps(MessageToDict(job), indent=2))
            else:
                _print_job(job)
                for k, v in sorted(job.result.figures.items()):
                    print(f"  {k}: {v}")
        elif args.action == "watch":
            job = client.wait(args.job_id, check=False)
            _print_job(job)
            return _exit_of(job)
        elif args.action == "cancel":
            _print_job(client.cancel(args.job_id))
        elif args.action == "resubmit":
            _print_job(client.resubmit(args.job_id))
    return 0


# ------------------------------------------------------------------------------------------------------------------
# unwind run --server
# ------------------------------------------------------------------------------------------------------------------
def _suffix(path: str | os.PathLike) -> str:
    name = Path(str(path).rstrip("/\\")).name.lower()
    for s in (".nii.gz", ".zarr", ".tif", ".tiff", ".nrrd", ".nii"):
        if name.endswith(s):
            return s
    return ".zarr"


def run_remote(args: argparse.Namespace) -> int:
    """``unwind run ... --server ADDR``: upload, the pipeline as a server job, download output and session.

    Takes the namespace of ``unwind run`` (plus ``server``, ``token``, ``tls``); writes the same files as the
    local run: the straight volume at ``--output`` and the session beside it (or at ``--session``), whose source
    is the local scan. Returns the same exit status as the local run: 0 ok, 3 partial (the job's ``status``).
    """
    import time
    from dataclasses import replace

    from ._cliargs import (
        _check_io,
        _check_session_path,
        _default_session_path,
        _endpoints_from_args,
        _pipeline_options,
        _reader_options,
    )
    from .io import open_volume
    from .io._atomic import check_writable
    from .io._formats import output_format
    from .io._volume import unit_label
    from .pipeline import exit_status
    from .session import Session, SourceInfo, save_session

    if args.mask and args.select:
        raise UnwindError("give either --mask MASK or --select A0,A1,A2 (segmentation), not both")
    if not args.mask and not args.select:
        raise UnwindError("say which specimen to straighten: --select A0,A1,A2 (a point inside it, full-resolution "
                          "voxels; the scan is segmented first) or --mask MASK (a mask from unwind select)")
    if getattr(args, "mask_label", None) is not None and not args.mask:
        raise UnwindError("--mask-label picks a label of --mask MASK: give the mask too")
    if args.mask and (args.features is not None or args.fill_holes or args.isovalue is not None
                      or args.level is not None):
        raise UnwindError("--features, --level, --isovalue and --fill-holes choose the segmentation; they do not "
                          "apply with --mask")
    output_format(args.output)
    check_writable(args.output, overwrite=args.overwrite)
    session_path = Path(args.session) if args.session else _default_session_path(args.output)
    target = _check_session_path(session_path, args.overwrite)
    _check_io([args.output, session_path], [args.input, args.mask])
    endpoints = _endpoints_from_args(args)
    say = (lambda *a: None) if args.quiet else print
    t0 = time.perf_counter()
    volume = open_volume(args.input, **_reader_options(args, args.input))
    with _client(args) as client:
        say(f"uploading {args.input} to {client.address}")
        vid = client.upload(volume, name=Path(str(args.input).rstrip("/")).name.split(".")[0] or "scan").volume_id
        mask_id = ""
        if args.mask:
            mask = open_volume(args.mask)
            if getattr(args, "mask_label", None) is not None:  # the label's voxels are uploaded, not the map
                from .io import Volume
                from .pipeline import pick_mask_label

                mask = Volume(pick_mask_label(mask.data, args.mask_label).astype("uint8"), spacing=mask.spacing,
                              origin=mask.origin, unit=mask.unit)
            mask_id = client.upload(mask, name="mask").volume_id
        job = client.pipeline(
            vid, select=args.select, mask_volume_id=mask_id, options=_pipeline_options(args),
            head=None if endpoints is None else endpoints.head, tail=None if endpoints is None else endpoints.tail,
            chain=None if endpoints is None else endpoints.chain, output_name="straight" + _suffix(args.output),
            name=Path(str(args.output)).name)
        # the pipeline's verdict, judged on the server as on this computer (a result without one raises before
        # anything is written: it is never taken for ok)
        verdict = client.specimen(job)
        for w in job.result.warnings:
            print(f"unwind: warning: {w}", file=sys.stderr)
        written = client.download(job.result.volume_id, args.output, overwrite=args.overwrite)
    from .client import _server_json

    remote = Session.from_dict(_server_json(job.result.session_json, "the session"))
    # the session describes the local scan (its checksum), so unwind straighten INPUT --session verifies
    session = Session(source=SourceInfo.from_path(args.input, volume=volume), deformation=remote.deformation,
                      segmentation=remote.segmentation, endpoints=remote.endpoints, twist=remote.twist,
                      notes=f"unwind run --server {args.server} (job {job.id})")
    written_session = save_session(session, target, overwrite=args.overwrite)
    result = replace(verdict, output=Path(written), session_path=Path(written_session), session=session)
    say(f"job {job.id} on {args.server}: length {result.length:.4g} {unit_label(result.unit)}, "
        f"{result.keyframes} keyframes, coverage {result.coverage:.3f}")
    say(f"straightened {args.input} -> {written}; session -> {written_session}; done in "
        f"{time.perf_counter() - t0:.1f} s")
    if result.status != "ok":  # the same line and exit status as the local run (cli._say_results)
        print(f"unwind: {result.status}: {_one_line(result.summary())}", file=sys.stderr)
    return exit_status([result])


# ------------------------------------------------------------------------------------------------------------------
def add_remote_commands(subparsers: Any) -> None:
    """Add ``serve``, ``submit`` and ``jobs`` to the ``unwind`` parser's subparsers."""
    from ._cliargs import _triple

    p = subparsers.add_parser("serve", help="run the gRPC server: every service in one process by default")
    p.add_argument("--data-root", default=None, metavar="DIR",
                   help="folder of the server's data: uploads, outputs, the job table (SQLite)")
    p.add_argument("--port", type=_port, default=50051, help="port (default 50051; 0: any free port)")
    p.add_argument("--listen", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1, this machine only; 0.0.0.0 needs --tokens)")
    p.add_argument("--service", action="append", choices=("volume", "segmentation", "skeleton", "warp", "jobs"),
                   help="run only this service (repeatable; the job service always runs)")
    p.add_argument("--scheduler", default=None, metavar="tcp://HOST:8786|threads",
                   help="where the jobs' chunked dask work (refine, straighten, bend, writes) runs. Default: a dask "
                        "LocalCluster the server starts and stops (one worker process, a thread per core), right "
                        "for one machine. tcp://HOST:PORT: an existing dask.distributed cluster (deploy/local.sh, "
                        "compose.yaml), for several machines; its workers must see the data root at the same path. "
                        "threads: dask threads inside each job worker, no cluster (small machines, tests)")
    p.add_argument("--tokens", default=None, metavar="FILE", help="tokens file: USER sha256:<hash> per line")
    p.add_argument("--add-token", default=None, metavar="USER",
                   help="print a new token for USER, store its hash in --tokens FILE, and exit")
    p.add_argument("--expires-days", type=_days, default=None, help="with --add-token: the token expires after this")
    p.add_argument("--tls-cert", default=None, metavar="PEM", help="TLS certificate chain (with --tls-key)")
    p.add_argument("--tls-key", default=None, metavar="PEM", help="TLS private key (with --tls-cert)")
    p.add_argument("--max-upload-bytes", type=_positive_int, default=8 * 1024**3,
                   help="largest upload, bytes (default 8 GiB; 0: no limit)")
    p.add_argument("--max-voxels", type=_positive_int, default=4 * 1024**3,
                   help="largest volume, voxels (default 4 Gi; 0: no limit)")
    p.add_argument("--max-message-bytes", type=_positive_int, default=64 * 1024**2,
                   help="largest gRPC message, bytes (default 64 MiB)")
    p.add_argument("--max-jobs-per-user", type=_positive_int, default=4,
                   help="jobs one user may have queued or running (default 4; 0: no limit)")
    p.add_argument("--max-running-per-user", type=_positive_int, default=None,
                   help="jobs of one user running at once (default: half of --workers, at least 1); another "
                        "user's queued job starts before a user's next one")
    p.add_argument("--max-uploads-per-user", type=_positive_int, default=None,
                   help="uploads of one user in progress at once (default 1; 0: no limit)")
    p.add_argument("--max-stored-bytes-per-user", type=_positive_int, default=None,
                   help="quota: bytes the server keeps for one user, uploads and job outputs (default 0: no limit)")
    p.add_argument("--max-calls-per-user", type=_positive_int, default=None,
                   help="calls of one user in progress at once, streams included (default 16; 0: no limit); "
                        "health checks are not counted")
    p.add_argument("--max-call-rate-per-user", type=_non_negative_float, default=None,
                   help="calls one user may start per second, bursts of two seconds' worth (default 50; 0: no "
                        "limit); a call over it waits for its turn, up to a second, holding one of the user's calls "
                        "in progress, and is refused past that; health checks are not counted")
    p.add_argument("--upload-idle-seconds", type=_non_negative_float, default=None,
                   help="an upload that sends nothing for this long is aborted, its import slot freed (default 30; "
                        "0: no limit)")
    p.add_argument("--download-idle-seconds", type=_non_negative_float, default=None,
                   help="a download whose client reads nothing for this long is cancelled (default 30; 0: no limit)")
    p.add_argument("--workers", type=int, default=2, help="jobs running at once (default 2)")
    p.add_argument("--imports", type=_positive_int, default=None,
                   help="uploads imported at once, in processes of their own so that a slow client holds no job "
                        "worker (default: as many as --workers); a further upload waits for a free one")
    p.add_argument("--drain", type=_non_negative_float, default=None,
                   help="on SIGTERM, seconds running jobs may finish before they are interrupted (default 30); a job "
                        "that does not stop within a few seconds more has its worker process killed")
    p.add_argument("--log-level", default="info", help="debug, info (default), warning, error")
    p.set_defaults(func=cmd_serve)

    p = subparsers.add_parser("submit", help="straighten on a server: a pipeline job, or a whole collection (--batch)")
    p.add_argument("input", nargs="?", help="a local scan to upload, a volume id (vol-...), or with --register a "
                                            "path under the server's data root")
    p.add_argument("--select", type=_triple, action="append", metavar="A0,A1,A2",
                   help="a point inside the specimen (full-resolution voxels, repeatable)")
    p.add_argument("--mask", default=None, help="the specimen's mask instead of segmenting")
    p.add_argument("--features", type=int, default=None, help="features the segmentation keeps (default 5)")
    p.add_argument("--isovalue", type=float, default=None, help="full-resolution threshold of the mask")
    p.add_argument("--fill-holes", action="store_true", help="fill cavities of the mask")
    p.add_argument("--head", type=_triple, default=None, metavar="A0,A1,A2", help="the head (default: suggested)")
    p.add_argument("--tail", type=_triple, default=None, metavar="A0,A1,A2", help="the tail (default: suggested)")
    p.add_argument("--order", type=int, choices=(0, 1, 3), default=1, help="interpolation order (default 1)")
    p.add_argument("--pad", type=int, default=0, help="extra slices at both ends")
    p.add_argument("--spacing", type=float, default=None, help="output voxel size")
    p.add_argument("--allow-folds", action="store_true", help="export even where the deformation folds")
    p.add_argument("--name", default=None, help="the output's file name on the server (default INPUT.zarr)")
    p.add_argument("--register", action="store_true", help="INPUT (and --mask) are paths under the data root")
    p.add_argument("--wait", action="store_true", help="follow the job to its end")
    p.add_argument("--batch", default=None, metavar="CSV",
                   help="a collection: CSV with columns scan, select ('all' or 'a0 a1 a2; ...'), name")
    p.add_argument("--max-parallel", type=int, default=4, help="with --batch: pipelines at once (default 4)")
    p.add_argument("--out-dir", default=None, help="with --batch: download outputs, sessions and summary.csv here")
    p.add_argument("--summary", default=None, help="with --batch: the summary CSV to write")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_client_options(p)
    p.set_defaults(func=cmd_submit)

    p = subparsers.add_parser("jobs", help="list, get, watch, cancel or resubmit jobs on a server")
    p.add_argument("action", choices=("list", "get", "watch", "cancel", "resubmit"), help="what to do")
    p.add_argument("job_id", nargs="?", help="the job's id (all but list)")
    p.add_argument("--limit", type=int, default=50, help="list: at most this many (default 50)")
    p.add_argument("--json", action="store_true", help="get: print the job as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    _add_client_options(p)
    p.set_defaults(func=cmd_jobs)


def add_run_server_options(p: argparse.ArgumentParser) -> None:
    """The options ``unwind run`` needs to run on a server: ``--server``, ``--token``, ``--tls``."""
    p.add_argument("--server", default=None, metavar="HOST:PORT",
                   help="run the pipeline on this server (upload, job, download) instead of here")
    _add_token_options(p)
