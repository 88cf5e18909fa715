"""NIfTI-1/2 volumes (``.nii``, ``.nii.gz``), through nibabel.

Axis order
----------
NIfTI stores voxel (i, j, k) with i the fastest axis in the file; nibabel indexes it as ``data[i, j, k]``.
napari-unwind's arrays put the slowest axis first (as NRRD read with ``index_order='C'`` does), so the volume is
nibabel's array transposed: ``volume.data[k, j, i] == img.dataobj[i, j, k]``. Spacing (the header's ``pixdim``
zooms) and origin (the affine's translation) are reversed the same way. The full affine is kept in
``Volume.metadata["affine"]`` (nibabel's (i, j, k) convention, RAS+ world).

Reading
-------
Lazy: chunks are read on demand through nibabel's array proxy (slabs of whole planes along axis0, i.e. along k, the
file's slowest axis). ``.nii`` files are memory mapped; a ``.nii.gz`` stream must be decompressed from its start
for every chunk read, so its chunks are made large (512 MiB): typical gzipped volumes are a single chunk. The chunk
holding the last plane reads on to the end of the stream, where gzip checks its CRC: a damaged ``.nii.gz`` is an
error, never other values. A ``.nii`` shorter than its header announces is refused when opened.
``scl_slope``/``scl_inter`` are applied; the integer type is kept when they are 1 and 0, or when both are integers
and the scaled range fits an integer type.

Writing
-------
Streams slab by slab along axis0 (the file order is exactly the C order of the transposed array), behind a
NIfTI-1 header whose sform and qform are ``diag(s2, s1, s0)`` plus the translation ``(o2, o1, o0)``, and whose
``xyzt_units`` record the unit. NIfTI-1 knows only metres, millimetres and micrometres: centimetres are written as
millimetres and nanometres as micrometres, with the spacing converted (same physical size).
"""

from __future__ import annotations

import contextlib
import gzip
import io
import os
import threading
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import dask.array as da
import nibabel as nib
import numpy as np
from dask.base import tokenize
from nibabel.imageglobals import logger as _nibabel_logger
from nibabel.nifti1 import Nifti1Extension
from nibabel.volumeutils import apply_read_scaling

from ..errors import InvalidInputError
from ..progress import Progress
from ._atomic import final_name
from ._files import ConfinementError, check_regular, current_confinement, open_regular
from ._lazy import write_slab_depth
from ._straight_record import parse_record, record_text, straightening_record
from ._volume import SUPPORTED_DTYPES, Volume, normalise_unit, warn_bad_spacing

__all__ = ["read_nifti", "write_nifti"]

_CHUNK_BYTES = 64 * 2**20
_QUIET_LOCK = threading.Lock()
_GZ_CHUNK_BYTES = 512 * 2**20
# NGFF unit -> (NIfTI xyz unit, factor applied to lengths)
_WRITE_UNITS = {
    "meter": ("meter", 1.0),
    "centimeter": ("mm", 10.0),
    "millimeter": ("mm", 1.0),
    "micrometer": ("micron", 1.0),
    "nanometer": ("micron", 1e-3),
    None: ("unknown", 1.0),
}


def _scaled_dtype(raw: np.dtype, slope: float, inter: float) -> np.dtype:
    """Voxel type of ``raw * slope + inter``: ``raw`` when unscaled, an integer type when exact, else float."""
    if slope == 1 and inter == 0:
        return raw
    if raw.kind in "iu" and float(slope).is_integer() and float(inter).is_integer():
        info = np.iinfo(raw)
        ends = (info.min * slope + inter, info.max * slope + inter)
        lo, hi = min(ends), max(ends)
        for cand in (raw, *(np.dtype(t) for t in ("u1", "i1", "u2", "i2", "u4", "i4"))):
            ci = np.iinfo(cand)
            if ci.min <= lo and hi <= ci.max:
                return cand
    return np.dtype("f8") if raw.itemsize >= 4 and raw.kind != "f" or raw == np.dtype("f8") else np.dtype("f4")


@contextlib.contextmanager
def _quiet_nibabel() -> Iterator[None]:
    with _QUIET_LOCK:
        disabled = _nibabel_logger.disabled
        _nibabel_logger.disabled = True
        try:
            yield
        finally:
            _nibabel_logger.disabled = disabled


def _as_type(block: np.ndarray, dtype: np.dtype) -> np.ndarray:
    if dtype.kind in "iu" and block.dtype.kind == "f":
        block = np.rint(block)
    return block.astype(dtype, copy=False)


def _damaged(path: Any, exc: BaseException) -> InvalidInputError:
    text = (str(exc).strip().splitlines() or [""])[0][:200]
    return InvalidInputError(f"{path}: cannot read its voxels ({type(exc).__name__}: {text}); the file is truncated "
                             "or damaged (or was changed since it was opened): copy it again")


class _ScaledProxy:
    """nibabel's ArrayProxy, sliced in file order (i, j, k), returning scaled voxels of one fixed type.

    Each read opens the file itself (:func:`~napari_unwind.io._files.open_regular`, under the confinement the
    volume was opened in: checked where the opened file lies) and gives nibabel that handle, never the path.
    """

    def __init__(self, proxy: Any, shape: tuple[int, int, int], extra: int, dtype: np.dtype, path: str = "",
                 gz: bool = False):
        # the proxy's layout, for a proxy of the same class over the handle each read opens
        self.spec = (tuple(proxy.shape), proxy.dtype, int(proxy.offset), proxy.slope, proxy.inter)
        self.order = getattr(proxy, "order", "F")
        self.proxy_class = type(proxy)
        self.shape = shape
        self.ndim = 3
        self.dtype = np.dtype(dtype)
        self.extra = extra  # trailing length-1 axes of the file (t, u...) to index with 0
        self.path = path
        self.gz = gz
        self.confine = current_confinement()  # opened confined: every read is (see _files.confined_reads)

    def __getitem__(self, key: Any) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        try:
            with open_regular(self.path, "NIfTI", confine=self.confine) as raw, \
                    (gzip.GzipFile(fileobj=raw, mode="rb") if self.gz else contextlib.nullcontext(raw)) as fh:
                proxy = self.proxy_class(fh, self.spec, mmap=False, order=self.order)
                block = np.asarray(proxy[key + (0,) * self.extra])
        except ConfinementError:
            raise  # outside the confinement: one line naming no path
        except (OSError, EOFError, ValueError, zlib.error) as exc:
            raise _damaged(self.path, exc) from None
        return _as_type(block, self.dtype)


class _GzipPlanes:
    """Voxels of a gzipped NIfTI in array order (k, j, i), decompressed plane range by plane range (the file opened
    anew at each read, under the confinement the volume was opened in, as :class:`_ScaledProxy` does).

    gzip streams cannot be read at random: each access decompresses from the start up to its last plane. The
    access that reaches the last plane reads on to the end of the stream, where gzip checks its CRC and length, so
    flipped or missing bytes are an error, never other voxel values.
    """

    def __init__(self, path: str, offset: int, file_dtype: np.dtype, shape: tuple[int, int, int], slope: float,
                 inter: float, dtype: np.dtype):
        self.path = str(path)
        self.offset = int(offset)
        self.file_dtype = np.dtype(file_dtype)
        self.shape = tuple(int(n) for n in shape)
        self.ndim = 3
        self.slope, self.inter = float(slope), float(inter)
        self.dtype = np.dtype(dtype)
        self.confine = current_confinement()  # opened confined: every read is (see _files.confined_reads)

    def __getitem__(self, key: Any) -> np.ndarray:
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (3 - len(key))
        k = key[0]
        single = isinstance(k, int | np.integer)
        k0, k1, step = (int(k) % self.shape[0], int(k) % self.shape[0] + 1, 1) if single else k.indices(self.shape[0])
        k1 = max(k0, k1)
        plane = self.shape[1] * self.shape[2] * self.file_dtype.itemsize
        want = (k1 - k0) * plane
        try:  # the file opened first and checked where it lies, gzip reading that handle
            with open_regular(self.path, "NIfTI", confine=self.confine) as raw, \
                    gzip.GzipFile(fileobj=raw, mode="rb") as fh:
                fh.seek(self.offset + k0 * plane)
                buf = fh.read(want)
                if len(buf) < want:
                    raise EOFError(f"the stream ends {want - len(buf)} bytes early")
                if k1 == self.shape[0]:
                    while fh.read(2**24):  # on to the end: gzip checks the CRC and length of the whole stream
                        pass
        except ConfinementError:
            raise  # outside the confinement: one line naming no path
        except (OSError, EOFError, ValueError, zlib.error) as exc:
            raise _damaged(self.path, exc) from None
        raw = np.frombuffer(buf, dtype=self.file_dtype).reshape((k1 - k0,) + self.shape[1:])[::step]
        if self.slope != 1 or self.inter != 0:
            raw = apply_read_scaling(raw, self.slope, self.inter)
        out = _as_type(raw, self.dtype)
        out = out[(slice(None),) + tuple(key[1:])]
        return out[0] if single else out


def _file_pixdims(path: Path, header_class: Any) -> list[float | None]:
    """pixdim[1..3] as the file states them, before nibabel's fix of zeros (None each when it cannot be read)."""
    import gzip

    try:
        opener = gzip.open if str(path).lower().endswith(".gz") else open
        with opener(path, "rb") as fh:
            raw = header_class.from_fileobj(fh, check=False)
        return [float(v) for v in raw["pixdim"][1:4]]
    except Exception:  # noqa: BLE001 - the header was read once already; this is only to say more
        return [None, None, None]


def read_nifti(path: Path, *, chunks: Any = None) -> Volume:
    """Open a NIfTI-1 or NIfTI-2 volume (``.nii`` or ``.nii.gz``) lazily.

    Parameters
    ----------
    path : Path
        The file.
    chunks : int or tuple of 3 int, optional
        Dask chunk shape in array order; default slabs of whole planes (64 MiB for ``.nii``, 512 MiB for
        ``.nii.gz``).

    Returns
    -------
    Volume
        Shape (K, J, I): nibabel's (I, J, K) array transposed, spacing ``zooms[2], zooms[1], zooms[0]``, origin
        the affine's translation reversed, unit from ``xyzt_units``.

    Raises
    ------
    InvalidInputError
        Not a NIfTI file, not 3D, or an unsupported voxel type (RGB, complex, 64-bit integers).
    """
    path = Path(path).expanduser().absolute()
    check_regular(path)
    try:
        with _quiet_nibabel():  # nibabel logs what it repairs in a broken header: our error says enough
            img = nib.load(str(path))
    except Exception as exc:  # nibabel raises ImageFileError, OSError, EOFError... for broken files
        raise InvalidInputError(f"{path} is not a readable NIfTI file ({exc}); is the copy complete?") from None
    if not isinstance(img, nib.Nifti1Image | nib.Nifti2Image):
        raise InvalidInputError(f"{path} holds a {type(img).__name__}, not a NIfTI image")
    hdr = img.header
    full_shape = tuple(int(s) for s in img.shape)
    if len(full_shape) < 3 or any(s != 1 for s in full_shape[3:]):
        raise InvalidInputError(
            f"{path} has shape {full_shape}; napari-unwind needs a 3D volume "
            "(extract one time point or channel first, e.g. with `fslroi` or nibabel)"
        )
    shape = full_shape[:3]
    if any(s < 1 for s in full_shape):
        raise InvalidInputError(f"{path}: the header's dimensions {full_shape} hold a size below 1; every axis has "
                                "at least one sample: the header is damaged")
    raw = np.dtype(img.get_data_dtype())
    if raw.fields is not None or raw.kind not in "iuf":
        raise InvalidInputError(f"{path}: voxel type {raw} is not supported; convert it to grey values first")
    raw = raw.newbyteorder("=")
    proxy = img.dataobj
    slope = float(getattr(proxy, "slope", 1.0))
    inter = float(getattr(proxy, "inter", 0.0))
    dtype = _scaled_dtype(raw, slope, inter)
    if dtype not in SUPPORTED_DTYPES:
        raise InvalidInputError(
            f"{path}: voxel type {dtype} is not supported; convert it to int32 or float (e.g. with nibabel)"
        )

    gz = path.name.lower().endswith(".gz")
    offset = int(getattr(proxy, "offset", 0))
    if not gz:
        need = offset + int(np.prod(full_shape, dtype=np.int64)) * raw.itemsize
        have = os.path.getsize(path)
        if have < need:
            raise InvalidInputError(f"{path} is truncated: its voxels end at byte {need} but the file has {have} "
                                    "bytes; the copy is incomplete: copy it again")
    if chunks is None:
        plane = shape[0] * shape[1] * dtype.itemsize
        depth = max(1, min(shape[2], (_GZ_CHUNK_BYTES if gz else _CHUNK_BYTES) // max(plane, 1)))
        file_chunks: Any = (shape[0], shape[1], depth)
    else:
        c = tuple(int(v) for v in np.broadcast_to(np.asarray(chunks), (3,)))
        file_chunks = c[::-1]
    st = os.stat(path)
    name = "nifti-" + tokenize(str(path), st.st_mtime_ns, st.st_size, str(dtype))
    if gz and getattr(proxy, "order", "F") == "F":
        # our own plane reader: nibabel stops reading before the gzip trailer, so damage would go unnoticed
        file_dtype = np.dtype(img.get_data_dtype())
        planes = _GzipPlanes(str(path), offset, file_dtype, shape[::-1], slope, inter, dtype)
        data = da.from_array(planes, chunks=file_chunks[::-1], name=name, meta=np.empty((0, 0, 0), dtype=dtype),
                             asarray=False)
    else:
        wrapped = _ScaledProxy(proxy, shape, len(full_shape) - 3, dtype, str(path), gz)
        data = da.from_array(wrapped, chunks=file_chunks, name=name, meta=np.empty((0, 0, 0), dtype=dtype),
                             asarray=False).transpose(2, 1, 0)

    zooms = [float(z) for z in hdr.get_zooms()[:3]]
    # nibabel sets a zero pixdim to 1 on load (a log line no one sees): read the file's own values to say so
    zooms = [z if r is None or (np.isfinite(r) and r > 0) else r for z, r in zip(zooms, _file_pixdims(path, type(hdr)))]
    for k, z in enumerate(zooms):
        if not (np.isfinite(z) and z > 0):
            warn_bad_spacing(path, 2 - k, z)
            zooms[k] = 1.0
    xyz_unit, _ = hdr.get_xyzt_units()
    try:
        unit = normalise_unit(xyz_unit)
    except InvalidInputError:
        unit = None
    affine = np.asarray(img.affine, dtype=float)
    origin = affine[:3, 3]
    if not np.all(np.isfinite(origin)):
        origin = np.zeros(3)
    return Volume(
        data,
        spacing=tuple(zooms[::-1]),
        unit=unit,
        origin=tuple(float(v) for v in origin[::-1]),
        source=str(path),
        format="nifti",
        metadata={
            "affine": affine.tolist(),
            "qform_code": int(hdr["qform_code"]),
            "sform_code": int(hdr["sform_code"]),
            "scl_slope": slope,
            "scl_inter": inter,
            "file_dtype": str(raw),
            "nifti_version": 2 if isinstance(img, nib.Nifti2Image) else 1,
            **({"unwind": {"straightening": _recorded(hdr)}} if _recorded(hdr) else {}),
        },
    )


#: The start of the comment extension holding a straight volume's record (napari_unwind.io._straight_record).
RECORD_PREFIX = "napari-unwind straightening "


def _recorded(hdr: Any) -> dict[str, Any] | None:
    """The straightening record of a header's comment extension written by :func:`write_nifti`, else None."""
    for ext in getattr(hdr, "extensions", ()):
        content = ext.get_content()
        if isinstance(content, bytes) and content.startswith(RECORD_PREFIX.encode()):
            return parse_record(content[len(RECORD_PREFIX):].rstrip(b"\x00"))
    return None


def _check_float32(path: Path, what: str, values: tuple[float, ...], unit: str, atol: float = 0.0) -> None:
    """Refuse, before anything is written, a spacing or origin that NIfTI's 32-bit floats cannot hold to relative
    1e-6 (or within ``atol``): an overflow, or a value below the smallest normal float32, which keeps fewer digits."""
    with np.errstate(over="ignore"):
        stored = np.asarray(values, dtype=np.float64).astype(np.float32).astype(np.float64)
    for axis, (v, f) in enumerate(zip(values, stored, strict=True)):
        if not (np.isfinite(f) and abs(f - v) <= max(1e-6 * abs(v), atol)):
            raise InvalidInputError(
                f"cannot write {final_name(path)}: NIfTI stores the {what} as 32-bit floats, which cannot hold "
                f"{v!r} {'' if unit == 'unknown' else unit + ' '}(axis{axis}; float32 holds about 1.2e-38 to "
                f"3.4e38); choose another unit or a format that keeps 64-bit numbers (OME-Zarr, NRRD, TIFF)"
            )


def write_nifti(volume: Volume, path: Path, *, compression_level: int = 4) -> Iterator[Progress]:
    """Write ``volume`` as NIfTI-1, gzipped when the target's name ends in ``.gz``, streaming slab by slab.

    Parameters
    ----------
    volume : Volume
        Shape (N0, N1, N2); stored as NIfTI (i, j, k) = (N2, N1, N0) with affine
        ``[[s2, 0, 0, o2], [0, s1, 0, o1], [0, 0, s0, o0]]``.
    path : Path
        The file to write (usually the temporary name chosen by :func:`~napari_unwind.io.write_volume`; the final
        name decides whether to gzip).
    compression_level : int
        gzip level 1 (fast) to 9 (small).

    Yields
    ------
    Progress
        One record per slab of planes written.
    """
    path = Path(path)
    if not 1 <= int(compression_level) <= 9:
        raise InvalidInputError(f"compression_level must be 1..9, got {compression_level}")
    n0, n1, n2 = volume.shape
    xyz_unit, factor = _WRITE_UNITS.get(volume.unit, ("unknown", 1.0))
    s0, s1, s2 = (s * factor for s in volume.spacing)
    o0, o1, o2 = (o * factor for o in volume.origin)
    _check_float32(path, "spacing", (s0, s1, s2), xyz_unit)
    _check_float32(path, "origin", (o0, o1, o2), xyz_unit, atol=1e-6 * min(s0, s1, s2))  # 0 and noise near it
    affine = np.array([[s2, 0, 0, o2], [0, s1, 0, o1], [0, 0, s0, o0], [0, 0, 0, 1]], dtype=float)

    dtype = volume.dtype.newbyteorder("<")
    hdr = nib.Nifti1Header(endianness="<")
    hdr.set_data_shape((n2, n1, n0))
    hdr.set_data_dtype(dtype)
    hdr.set_zooms((s2, s1, s0))
    hdr.set_qform(affine, code=1)
    hdr.set_sform(affine, code=1)
    hdr.set_xyzt_units(xyz=xyz_unit, t="unknown")
    hdr["descrip"] = b"napari-unwind"
    record = straightening_record(volume)
    if record is not None:  # a comment extension holding the straightening record
        hdr.extensions.append(Nifti1Extension("comment", (RECORD_PREFIX + record_text(record)).encode()))
    hdr["vox_offset"] = 352 + hdr.extensions.get_sizeondisk()
    buffer = io.BytesIO()
    hdr.write_to(buffer)  # the header, then 4 zero bytes (no extension) or the extensions
    head = buffer.getvalue()

    gz = final_name(path).lower().endswith(".gz")
    depth = write_slab_depth(volume)
    total = -(-n0 // depth)
    with open(path, "wb") as raw_fh:
        fh: Any = gzip.GzipFile(fileobj=raw_fh, mode="wb", compresslevel=int(compression_level), mtime=0) \
            if gz else raw_fh
        try:
            fh.write(head)
            for i, z0 in enumerate(range(0, n0, depth)):
                z1 = min(n0, z0 + depth)
                slab = np.ascontiguousarray(np.asarray(volume.data[z0:z1].compute()), dtype=dtype)
                fh.write(memoryview(slab).cast("B"))
                yield Progress("write nifti", i + 1, total, f"planes {z0}-{z1 - 1} of {n0}")
        finally:
            if gz:
                fh.close()
