"""gRPC services of napari-unwind (import name ``unwind_services``; source folder ``services/``).

Thin servicers over :mod:`napari_unwind`: protobuf in, one core call (or a job driving a core generator),
protobuf out. Contracts: ``protos/unwind/v1``; stubs in :mod:`unwind_services._proto` (from
``scripts/gen_protos.py``).

- :mod:`.server`      :class:`UnwindServer`: services, health, reflection, TLS, graceful shutdown
- :mod:`.interceptor` the one interceptor: tokens, malformed messages, domain errors -> status codes
- :mod:`.jobs`        the job runner (threads), durable in :mod:`.store` (SQLite, WAL)
- :mod:`.tasks`       the job kinds, each a generator over core generators
- :mod:`.servicers`   VolumeService, SegmentationService, SkeletonService, WarpService, JobService
"""

from .server import ServerConfig, UnwindServer

__all__ = ["ServerConfig", "UnwindServer"]
