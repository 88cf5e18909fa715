"""Build and run the gRPC server: services, health, reflection, the interceptor, TLS and graceful shutdown."""

from __future__ import annotations

import ipaddress
import logging
import signal
import sys
import threading
import warnings
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from napari_unwind.errors import InvalidInputError

from .auth import TokenAuth
from .catalog import Catalog, Limits
from .fairness import CallLimiter
from .interceptor import ServiceInterceptor
from .jobs import JobManager
from .paths import DataRoot, RootLock
from .servicers import SERVICES
from .store import Store

__all__ = ["ServerConfig", "UnwindServer", "LocalDask", "check_scheduler"]

log = logging.getLogger("unwind_services")


@dataclass
class ServerConfig:
    """Everything ``unwind serve`` takes."""

    data_root: Path
    port: int = 50051
    listen: str = "127.0.0.1"
    services: Sequence[str] = ()
    scheduler: str | None = None  # None: a LocalCluster of this server; "threads"; or "tcp://host:port"
    tokens: Path | None = None
    tls_cert: Path | None = None
    tls_key: Path | None = None
    limits: Limits = field(default_factory=Limits)
    workers: int = 2
    imports: int = 0  # uploads imported at once, in their own processes (0: as many as workers)
    dask_threads: int = 0  # threads of the in-process LocalCluster's worker (0: one per core)
    grpc_threads: int = 64
    drain_seconds: float = 30.0  # on SIGTERM: running jobs may finish for this long, then they are interrupted


def _is_loopback(host: str) -> bool:
    if host in ("localhost", "127.0.0.1", "::1", "[::1]"):
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_tls(cert: Path, key: Path) -> None:
    """Refuse, in one line and before anything binds, a certificate or key that cannot serve TLS: a missing or
    unreadable file, one that is not PEM, or a key that is not the certificate's (Python's ``ssl`` loads the pair
    as gRPC would, and says which)."""
    import ssl

    for what, path in (("--tls-cert", cert), ("--tls-key", key)):
        if not Path(path).is_file():
            raise InvalidInputError(f"{what} {path} does not exist or is not a file")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        context.load_cert_chain(str(cert), str(key))
    except ssl.SSLError as exc:
        reason = (exc.reason or str(exc)).replace("_", " ").lower()
        if "key values mismatch" in reason:
            problem = f"the key {key} is not the key of the certificate {cert}"
        elif "pem" in reason or "no start line" in reason:
            problem = f"{cert} or {key} is not a PEM certificate or key ({reason})"
        else:
            problem = f"{cert} and {key} cannot serve TLS ({reason})"
        raise InvalidInputError(f"{problem}: give --tls-cert the PEM certificate (chain) and --tls-key its own "
                                "private key, unencrypted") from None
    except OSError as exc:
        raise InvalidInputError(f"cannot read {cert} or {key}: {exc.strerror or exc}") from None


#: gRPC's server reflection v1: the same messages as v1alpha (grpcio-reflection ships v1alpha only), so the v1alpha
#: servicer answers on the v1 method too, for clients (grpcurl, Postman, newer grpc_cli) that ask v1 first.
REFLECTION_V1 = "grpc.reflection.v1.ServerReflection"


def _enable_reflection(server: grpc.Server, names: list[str]) -> None:
    from grpc_reflection.v1alpha import reflection_pb2

    names = [*names, reflection.SERVICE_NAME, REFLECTION_V1]
    servicer = reflection.ReflectionServicer(names)
    reflection.enable_server_reflection(names, server)  # v1alpha
    handler = grpc.stream_stream_rpc_method_handler(
        servicer.ServerReflectionInfo,
        request_deserializer=reflection_pb2.ServerReflectionRequest.FromString,
        response_serializer=reflection_pb2.ServerReflectionResponse.SerializeToString)
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(
        REFLECTION_V1, {"ServerReflectionInfo": handler}),))


def _warm_imports() -> None:
    import importlib

    for name in ("napari_unwind.segmentation", "napari_unwind.skeleton", "napari_unwind.warp",
                 "napari_unwind.session"):
        try:
            importlib.import_module(name)
        except Exception:  # noqa: BLE001 - a broken import shows in the first job that needs it
            log.exception("importing %s failed", name)


#: ``--scheduler`` values that keep dask in the job workers' own threads (no cluster).
THREADS = ("threads",)


def check_scheduler(scheduler: str | None) -> None:
    """None (the in-process LocalCluster), ``"threads"``, or a cluster address; anything else is refused."""
    if scheduler is None or scheduler in THREADS:
        return
    if not isinstance(scheduler, str) or "://" not in scheduler or not scheduler.split("://", 1)[1]:
        raise InvalidInputError(f"--scheduler must be 'threads' or a dask scheduler address such as "
                                f"tcp://host:8786 (default: a LocalCluster in the server), got {scheduler!r}")


class LocalDask:
    """The default scheduler: a dask.distributed LocalCluster started by the server, closed with it.

    One worker process (under a nanny, which restarts it if it dies) with one thread per core: the chunked work
    runs outside the server's process, so it never holds the server's GIL (gRPC answers stay fast), and all
    chunks of a computation live in one process, so no chunk is copied between workers. Its memory limit is
    half of this machine's memory (the job workers, which write the slabs, and the server need the rest); past
    it the worker spills to ``.unwind/dask`` under the data root, then is restarted. No dashboard.
    """

    def __init__(self, root: DataRoot, threads: int = 0):
        import os

        import psutil
        from distributed import LocalCluster

        self.threads = int(threads) or os.cpu_count() or 1
        self.memory_limit = int(psutil.virtual_memory().total // 2)
        space = root.private / "dask"
        space.mkdir(exist_ok=True)
        self.cluster = LocalCluster(
            n_workers=1, threads_per_worker=self.threads, processes=True, host="127.0.0.1", scheduler_port=0,
            dashboard_address=None, memory_limit=self.memory_limit, local_directory=str(space),
            silence_logs=logging.WARNING,
            # no dashboard; the scheduler's small HTTP server (health, metrics) on a free loopback port, not 8787
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0"})
        self.address = self.cluster.scheduler_address

    def close(self) -> None:
        self.cluster.close(timeout=30)


def _stream_limit(calls_per_user: int) -> list[tuple[str, int]]:
    """HTTP/2's limit of concurrent streams per connection, set to the calls a user may have in progress (plus the
    health checks a prober may share the connection with): a client's further calls wait in its own transport instead
    of reaching the server only to be refused (which costs the server as much as serving them)."""
    return [("grpc.max_concurrent_streams", int(calls_per_user) + 4)] if calls_per_user else []


class UnwindServer:
    """One process serving the chosen services over one port."""

    def __init__(self, config: ServerConfig):
        self.config = config
        names = list(config.services) or list(SERVICES)
        unknown = [n for n in names if n not in SERVICES]
        if unknown:
            raise InvalidInputError(f"unknown service {unknown[0]!r}; choose from {', '.join(SERVICES)}")
        if "jobs" not in names:
            names.append("jobs")  # every long operation is a job: the job service comes with any other
        check_scheduler(config.scheduler)
        if (config.tls_cert is None) != (config.tls_key is None):
            raise InvalidInputError("TLS needs both --tls-cert and --tls-key")
        if not _is_loopback(config.listen) and config.tokens is None:
            raise InvalidInputError(f"listening on {config.listen} (beyond this machine) needs --tokens FILE: "
                                    "without tokens anyone who reaches the port could use the server")
        if config.tls_cert is not None:
            check_tls(Path(config.tls_cert), Path(config.tls_key))
        elif not _is_loopback(config.listen):
            log.warning("listening on %s beyond this machine without TLS: tokens and scans cross the network in "
                        "clear text; give --tls-cert and --tls-key", config.listen)
        self.root = DataRoot(config.data_root)
        self.lock = RootLock(self.root)  # before the database: a second server must not touch the jobs
        try:
            self.store = Store(self.root.database)
            self.catalog = Catalog(self.store, self.root, config.limits)
            self.auth = TokenAuth(config.tokens)
            self.jobs = JobManager(self.catalog, workers=config.workers, scheduler=config.scheduler,
                                   imports=config.imports or None)
            size = config.limits.message_bytes
            self.server = grpc.server(
                ThreadPoolExecutor(max_workers=config.grpc_threads, thread_name_prefix="unwind-rpc"),
                # the user's calls in progress are counted inside the first, which knows the user
                interceptors=[ServiceInterceptor(self.auth, self.root), CallLimiter(config.limits.max_calls_per_user,
                                                                                config.limits.max_call_rate_per_user)],
                options=[("grpc.max_receive_message_length", size), ("grpc.max_send_message_length", size),
                         ("grpc.so_reuseport", 0)] + _stream_limit(config.limits.max_calls_per_user),
                maximum_concurrent_rpcs=config.grpc_threads * 4,
            )
            self.health = health.HealthServicer(experimental_non_blocking=True)
            health_pb2_grpc.add_HealthServicer_to_server(self.health, self.server)
            full_names = []
            for name in names:
                full, factory, add = SERVICES[name]
                add(factory(self.catalog, self.jobs), self.server)
                full_names.append(full)
            self.service_names = full_names
            _enable_reflection(self.server, full_names + [health_pb2.DESCRIPTOR.services_by_name["Health"].full_name])
            host = config.listen if ":" not in config.listen else f"[{config.listen}]"
            address = f"{host}:{config.port}"
            if config.tls_cert is not None:
                creds = grpc.ssl_server_credentials([(Path(config.tls_key).read_bytes(),
                                                      Path(config.tls_cert).read_bytes())])
                self.port = self.server.add_secure_port(address, creds)
            else:
                self.port = self.server.add_insecure_port(address)
            if not self.port:
                raise InvalidInputError(f"cannot listen on {address} (in use, or not an address of this machine)")
            self.address = f"{config.listen}:{self.port}"
            self.lock.describe(self.address)
        except BaseException:
            self.lock.release()
            raise
        self.dask: LocalDask | None = None
        self._stopped = threading.Event()

    def _start_scheduler(self) -> None:
        """The job workers' scheduler: a LocalCluster (default), an external cluster (checked now), or threads."""
        scheduler = self.config.scheduler
        if scheduler is None:
            self.dask = LocalDask(self.root, self.config.dask_threads)
            self.jobs.scheduler = self.dask.address
            log.info("dask LocalCluster at %s: 1 worker process, %d threads, memory limit %.1f GiB",
                     self.dask.address, self.dask.threads, self.dask.memory_limit / 2**30)
        elif scheduler in THREADS:
            self.jobs.scheduler = None
            log.info("dask: threads inside each job worker (no cluster)")
        else:
            from napari_unwind.scheduler import use_scheduler

            with use_scheduler(scheduler):  # fail now, with a clear message, if it cannot be reached
                pass
            self.jobs.scheduler = scheduler
            log.info("dask cluster at %s", scheduler)

    def start(self) -> None:
        warnings.filterwarnings("ignore", category=UserWarning, module="napari_unwind.warp")
        # the core's heavy modules (numba kernels, the tet mesher) load once, now, not in the first job
        threading.Thread(target=_warm_imports, name="unwind-warm", daemon=True).start()
        self._start_scheduler()
        try:
            self.jobs.start()
        except BaseException:
            self._close_scheduler()
            self.lock.release()
            raise
        self.server.start()
        for name in ["", *self.service_names]:
            self.health.set(name, health_pb2.HealthCheckResponse.SERVING)
        log.info("serving %s on %s (data root %s)", ", ".join(self.service_names), self.address, self.root.root)

    def stop(self, grace: float | None = None) -> None:
        """Graceful shutdown: NOT_SERVING, no new calls, running jobs drained (up to the grace) or interrupted."""
        if self._stopped.is_set():
            return
        grace = self.config.drain_seconds if grace is None else grace
        self.health.enter_graceful_shutdown()
        stopping = self.server.stop(grace)
        self.jobs.shutdown(drain_seconds=grace)  # the jobs end first: they compute on the cluster
        stopping.wait()
        self._close_scheduler()
        self.store.close()
        self.lock.release()
        self._stopped.set()

    def _close_scheduler(self) -> None:
        if self.dask is not None:
            try:
                self.dask.close()
            except Exception:  # noqa: BLE001 - shutting down anyway; the worker dies with the server
                log.exception("closing the dask LocalCluster failed")
            self.dask = None

    def wait(self) -> None:
        self._stopped.wait()

    def serve_forever(self) -> None:
        """Start, then stop on SIGTERM or SIGINT."""
        def on_signal(signum, frame):
            log.info("signal %s: shutting down (drain %s s)", signum, self.config.drain_seconds)
            threading.Thread(target=self.stop, daemon=True).start()

        signal.signal(signal.SIGTERM, on_signal)
        signal.signal(signal.SIGINT, on_signal)
        self.start()
        print(f"unwind serve: listening on {self.address}", flush=True)
        while not self._stopped.wait(timeout=0.5):
            pass
        print("unwind serve: stopped", file=sys.stderr, flush=True)
