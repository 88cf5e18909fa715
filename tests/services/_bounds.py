"""Helpers of the bounds and fuzz tests: the documented bounds of every request field (read from the .proto
comments, the contract, not from the server's code), an in-process server, and raw calls of any method."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
from google.protobuf.descriptor import FieldDescriptor as F

from unwind_services._proto.unwind.v1 import jobs_pb2, segmentation_pb2, skeleton_pb2, volume_pb2, warp_pb2

PROTOS = Path(__file__).resolve().parents[2] / "protos" / "unwind" / "v1"
MODULES = (jobs_pb2, segmentation_pb2, skeleton_pb2, volume_pb2, warp_pb2)
BAD = (grpc.StatusCode.INTERNAL, grpc.StatusCode.UNKNOWN)


def documented_bounds() -> dict[str, str]:
    """``"Message.field"`` -> the text after ``// Bounds:`` on the comment lines above the field."""
    out: dict[str, str] = {}
    for path in sorted(PROTOS.glob("*.proto")):
        message, pending = None, None
        for line in path.read_text().splitlines():
            m = re.match(r"^message (\w+) \{", line)
            if m:
                message = m.group(1)
            b = re.match(r"^\s*// Bounds: (.*)\.$", line)
            if b:
                pending = b.group(1)
                continue
            f = re.match(r"^\s+(?:optional |repeated )?[\w.<>, ]+ (\w+) = \d+;", line)
            if f and message:
                if pending is not None:
                    out[f"{message}.{f.group(1)}"] = pending
                pending = None
            if line.startswith("}"):
                message = None
    return out


def methods():
    """Every method of every service: (service descriptor, method descriptor)."""
    return [(s, m) for mod in MODULES for s in mod.DESCRIPTOR.services_by_name.values() for m in s.methods]


def request_fields():
    """Every field reachable from a request message: ``"Message.field"`` -> (method, path of field descriptors),
    the shortest path from any method (JobService.Submit first, so job specs go through Submit)."""
    out: dict[str, tuple] = {}
    order = sorted(methods(), key=lambda sm: (sm[1].name != "Submit",))
    for svc, method in order:
        todo = [(method.input_type, ())]
        while todo:
            desc, path = todo.pop(0)
            for fd in desc.fields:
                key = f"{desc.name}.{fd.name}"
                if key in out and len(out[key][1]) <= len(path):
                    continue
                out[key] = ((svc, method), path + (fd,))
                if fd.type == F.TYPE_MESSAGE and fd.message_type.name not in [p.message_type.name for p in path
                                                                            if p.type == F.TYPE_MESSAGE]:
                    todo.append((fd.message_type, path + (fd,)))
    return out


#: Fields a message needs within their bounds for the test of another field to reach that field's check.
BASELINE = {"UploadHeader": {"shape": [1, 1, 1]}}


def _baseline(m):
    for name, value in BASELINE.get(m.DESCRIPTOR.name, {}).items():
        getattr(m, name).extend(value)


def build(method, path, value):
    """The method's request with the field at ``path`` set to ``value`` (a list for a repeated field)."""
    from google.protobuf import message_factory

    cls = message_factory.GetMessageClass(method.input_type)
    msg = cls()
    m = msg
    for fd in path[:-1]:
        if fd.is_repeated:
            m = getattr(m, fd.name).add()
        else:
            sub = getattr(m, fd.name)
            sub.SetInParent()
            m = sub
        _baseline(m)
    leaf = path[-1]
    if leaf.name in BASELINE.get(m.DESCRIPTOR.name, {}):
        m.ClearField(leaf.name)
    if leaf.is_repeated:
        target = getattr(m, leaf.name)
        if leaf.type == F.TYPE_MESSAGE:
            for _ in range(value):
                target.add()
        else:
            target.extend(value)
    elif leaf.type == F.TYPE_MESSAGE:
        getattr(m, leaf.name).SetInParent()
    else:
        setattr(m, leaf.name, value)
    return msg


def call(channel, svc, method, request, timeout=60.0):
    """(status code or None, details) of one call of any method with ``request``."""
    name = f"/{svc.full_name}/{method.name}"
    ser, de = (lambda m: m.SerializeToString()), (lambda b: b)
    try:
        if method.client_streaming:
            channel.stream_unary(name, request_serializer=ser, response_deserializer=de)(iter([request]),
                                                                                          timeout=timeout)
        elif method.server_streaming:
            for _ in channel.unary_stream(name, request_serializer=ser, response_deserializer=de)(request,
                                                                                                  timeout=timeout):
                pass
        else:
            channel.unary_unary(name, request_serializer=ser, response_deserializer=de)(request, timeout=timeout)
    except grpc.RpcError as exc:
        return exc.code(), exc.details() or ""
    return None, ""


@dataclass
class Documented:
    """A field's documented bound, parsed: ``kind`` is "range", "finite", "text", "items", "any", "enum" or
    "bytes"."""

    kind: str
    lo: float | None = None
    hi: float | None = None
    max_bytes: int = 0
    path: bool = False
    max_items: int | None = None
    counts: tuple[int, ...] = ()
    each: Documented | None = None


def parse(text: str) -> Documented:
    m = re.fullmatch(r"(-?[\d.e]+)\.\.(-?[\d.e]+)", text)
    if m:
        return Documented("range", float(m.group(1)), float(m.group(2)))
    if text == "a finite number":
        return Documented("finite")
    m = re.fullmatch(r"at most (\d+) bytes, no NUL(, each folder or file name at most 255 bytes)?", text)
    if m:
        return Documented("text", max_bytes=int(m.group(1)), path=bool(m.group(2)))
    m = re.fullmatch(r"(?:at most (\d+)|exactly ([\d or]+)) items(?:, each (.*))?", text)
    if m:
        counts = tuple(int(c) for c in m.group(2).split(" or ")) if m.group(2) else ()
        return Documented("items", max_items=int(m.group(1)) if m.group(1) else None, counts=counts,
                          each=parse(m.group(3)) if m.group(3) else None)
    if text in ("any", "a defined value", "the message size limit"):
        return Documented({"any": "any", "a defined value": "enum", "the message size limit": "bytes"}[text])
    raise AssertionError(f"a bound the tests cannot read: {text!r}")


def small_server(tmp: Path):
    """An in-process server (dask in threads, one worker) on a data root under ``tmp`` holding a 6x5x4 scan
    ``scans/small.tif``; yields ``(server, channel)`` and stops both (a module fixture's body)."""
    from napari_unwind.io import write_volume
    from unwind_services.server import ServerConfig, UnwindServer

    data = Path(tmp) / "data"
    (data / "scans").mkdir(parents=True)
    write_volume(np.arange(6 * 5 * 4, dtype=np.uint16).reshape(6, 5, 4), data / "scans" / "small.tif")
    srv = UnwindServer(ServerConfig(data_root=data, port=0, scheduler="threads", workers=1))
    srv.start()
    channel = grpc.insecure_channel(f"127.0.0.1:{srv.port}", options=[
        ("grpc.max_send_message_length", 64 * 2**20), ("grpc.max_receive_message_length", 64 * 2**20)])
    yield srv, channel
    channel.close()
    srv.stop(0)
