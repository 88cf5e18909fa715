"""gRPC services of napari-unwind (import name ``unwind_services``; source folder ``services/``).

Thin servicers over :mod:`napari_unwind`: protobuf in, one core call, protobuf out. They arrive with the services
issue; the core they wrap is built first.
"""
