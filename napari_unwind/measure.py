"""Measurements along the centreline of a deformation: a profile with one row per station ``s``.

Per station (``s`` from 0 to the deformation's length, one output spacing apart):

- the curve: arc length ``s``, the centre (physical, array axis order), the curvature and torsion of the centre
  curve (a cubic spline through the keyframe positions, parametrised by their arc lengths), the twist the frames
  apply (their roll about the tangent against rotation-minimising frames, cumulated from ``s = 0``, degrees) and
  its rate;
- the cage: its half-sizes and centre offset in the cross-section;
- with a mask: the specimen's cross-section in the straight space (the mask resampled linearly, so a voxel cut by
  the boundary counts by its share): area, perimeter (marching squares at 0.5), equivalent radius, the centroid's
  offset from the curve, major and minor axes (4 sqrt of the area-weighted second moments' eigenvalues: a disk of
  radius r gives 2r), eccentricity and the major axis's angle to u;
- with labels: the area of each label (nearest-neighbour resampling);
- with channels: intensity statistics (mean, standard deviation, minimum, maximum) of each channel over the
  cross-section (inside the mask when one is given, the whole cage otherwise).

The straight slices are computed chunk by chunk (:func:`napari_unwind.warp.straighten`), so memory is bounded by one
chunk of the straight volume per input. Units: lengths in the deformation's unit, areas in its square, curvature
and torsion in its inverse, angles in degrees.

Outputs (:meth:`Profile.save` picks one by the suffix): CSV (:meth:`Profile.to_csv`, units in the header), Parquet
(:meth:`Profile.to_parquet`, needs ``pyarrow``: the ``tables`` extra; each field's unit in its metadata) and a PNG
plot of the profiles against ``s`` (:meth:`Profile.plot`, needs ``matplotlib``: the ``plot`` extra). Each is
written atomically, and the same profile gives the same bytes. :func:`read_profile` reads CSV and Parquet back.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Generator, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .deformation import Deformation
from .errors import InvalidInputError
from .progress import Progress
from .progress import run as run_with_progress

__all__ = ["Profile", "measure", "measure_iter", "curve_geometry", "read_profile", "profile_format", "MAX_LABELS",
           "PROFILE_FORMATS"]

#: At most this many labels get an area column each (a label image with more is refused, naming the count).
MAX_LABELS = 256

#: A profile's outputs by suffix: the two tables and the plot.
PROFILE_FORMATS = {".csv": "CSV", ".parquet": "Parquet", ".png": "PNG"}


@dataclass(frozen=True)
class Profile:
    """A table of measurements along the centreline.

    Attributes
    ----------
    columns : dict of str to ndarray, each shape (K,)
        Column name to values, in the order written; ``"s"`` first.
    units : dict of str to str
        Column name to its unit ("" for dimensionless numbers).
    unit : str or None
        The length unit of the deformation.
    meta : dict of str to str
        Provenance (the session, the mask, the channels: what the caller records), written in the Parquet
        schema's metadata; never anything that changes between two runs of the same measurement.
    """

    columns: dict[str, np.ndarray]
    units: dict[str, str] = field(default_factory=dict)
    unit: str | None = None
    meta: dict[str, str] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.columns["s"])

    def __getitem__(self, name: str) -> np.ndarray:
        return self.columns[name]

    @property
    def names(self) -> list[str]:
        return list(self.columns)

    def header(self) -> list[str]:
        """Column names with their units, as written to CSV: ``"area [mm^2]"``."""
        return [f"{n} [{self.units[n]}]" if self.units.get(n) else n for n in self.columns]

    def csv_text(self) -> str:
        """The table as CSV text: a header of names with units, then one row per station (9 significant digits,
        empty where there is no value). The same text on every face: the command line, the API and the server."""
        import csv
        import io

        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.header())
        table = np.column_stack([np.asarray(v, dtype=float) for v in self.columns.values()])
        for row in table:
            w.writerow(["" if not np.isfinite(x) else f"{x:.9g}" for x in row])
        return buf.getvalue()

    def to_csv(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write :meth:`csv_text` to ``path`` atomically."""
        from .io._atomic import atomic_output

        path = Path(path)
        with atomic_output(path, overwrite=overwrite) as tmp:
            Path(tmp).write_text(self.csv_text(), encoding="utf-8")
        return path

    def to_parquet(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the table to ``path`` as Parquet, atomically (needs ``pyarrow``: ``pip install
        napari-unwind[tables]``).

        One float64 column per profile column, in order; a value that is not finite (no section at a station) is
        null, as it is empty in the CSV. Each field's metadata holds its unit (``b"unit"``, ``""`` for a
        dimensionless number); the schema's metadata holds the length unit (``b"unit"``) and, under
        ``b"napari_unwind"``, JSON with the writer's version, the units and :attr:`meta`. The same profile gives
        the same bytes.
        """
        from .io._atomic import atomic_output

        pa, pq = _need("pyarrow", "tables", "Parquet"), _need("pyarrow.parquet", "tables", "Parquet")
        path = Path(path)
        table = self._arrow_table(pa)
        with atomic_output(path, overwrite=overwrite) as tmp:
            pq.write_table(table, str(tmp), compression="zstd")
        return path

    def _arrow_table(self, pa: Any) -> Any:
        from . import __version__

        fields, arrays = [], []
        for name, values in self.columns.items():
            v = np.ascontiguousarray(values, dtype=np.float64)
            arrays.append(pa.array(v, type=pa.float64(), mask=~np.isfinite(v)))
            fields.append(pa.field(name, pa.float64(), metadata={b"unit": self.units.get(name, "").encode()}))
        about = {"format": "napari-unwind profile", "version": __version__, "unit": self.unit,
                 "units": {n: self.units.get(n, "") for n in self.columns}, "meta": dict(self.meta)}
        schema = pa.schema(fields, metadata={b"unit": (self.unit or "").encode(),
                                             b"napari_unwind": json.dumps(about, sort_keys=True).encode()})
        return pa.Table.from_arrays(arrays, schema=schema)

    def save(self, path: str | os.PathLike, *, overwrite: bool = False) -> Path:
        """Write the profile in the format its suffix names: ``.csv``, ``.parquet`` or ``.png`` (the plot)."""
        kind = profile_format(path)
        if kind == ".csv":
            return self.to_csv(path, overwrite=overwrite)
        if kind == ".parquet":
            return self.to_parquet(path, overwrite=overwrite)
        self.plot(path, overwrite=overwrite)
        return Path(path)

    def plot(self, path: str | os.PathLike | None = None, *, columns: Iterable[str] | None = None,
             figure: Any = None, overwrite: bool = False) -> Any:
        """Plot the profiles against the arc length ``s``, one panel per quantity group (needs ``matplotlib``:
        ``pip install napari-unwind[plot]``).

        Panels, those present only: curvature and torsion; twist; area with the equivalent radius (right axis);
        major and minor axes with the eccentricity (right axis); each channel's mean (with mean +- std shaded);
        the area of each label. Every axis is labelled with its unit.

        Parameters
        ----------
        path : str or PathLike, optional
            A ``.png`` file to write (atomically; the same profile gives the same bytes).
        columns : iterable of str, optional
            Plot these columns only (each in its group's panel; a column of no group gets a panel per unit).
        figure : matplotlib.figure.Figure, optional
            Draw into this figure (cleared first; the dock's canvas), else a new one sized for the panels.
        overwrite : bool
            Replace an existing ``path``.

        Returns
        -------
        matplotlib.figure.Figure
            The figure; each curve's ``gid`` is its column's name.
        """
        if path is not None and Path(path).suffix.lower() != ".png":
            raise InvalidInputError(f"the plot is written as PNG: give a path ending in .png, got {path}")
        panels = _plot_panels(self, columns)
        _need("matplotlib", "plot", "the plot")
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        with matplotlib.rc_context(_PLOT_STYLE):
            if figure is None:
                figure = Figure(figsize=(8.0, 0.9 + 1.9 * len(panels)), dpi=100, layout="constrained")
                FigureCanvasAgg(figure)
            else:
                figure.clear()
            _draw_panels(figure, self, panels)
            if path is not None:
                from .io._atomic import atomic_output

                with atomic_output(Path(path), overwrite=overwrite) as tmp:
                    figure.savefig(str(tmp), format="png", metadata={"Software": None})
        return figure


def profile_format(path: str | os.PathLike, *, formats: Iterable[str] = tuple(PROFILE_FORMATS)) -> str:
    """The suffix (lower case) of a profile output among ``formats``, or a one-line error listing them."""
    formats = tuple(formats)
    suffix = Path(path).suffix.lower()
    if suffix not in formats:
        names = " or ".join(f"{PROFILE_FORMATS[f]} ({f})" for f in formats)
        raise InvalidInputError(f"a profile is written as {names}: give a path ending in "
                                f"{' or '.join(formats)}, got {os.fspath(path)}")
    return suffix


def read_profile(path: str | os.PathLike) -> Profile:
    """Read a profile written by :meth:`Profile.to_csv` or :meth:`Profile.to_parquet` (by its suffix).

    A CSV has no length unit of its own: the profile's ``unit`` is then the label of ``s``'s unit ("um"). Empty
    cells and nulls read as NaN.
    """
    import csv

    kind = profile_format(path, formats=(".csv", ".parquet"))
    path = Path(path)
    if not path.is_file():
        raise InvalidInputError(f"no profile at {path}")
    if kind == ".parquet":
        pq = _need("pyarrow.parquet", "tables", "Parquet")
        table = pq.read_table(str(path))
        cols = {f.name: np.asarray(table.column(f.name).to_numpy(zero_copy_only=False), dtype=np.float64)
                for f in table.schema}
        units = {f.name: (f.metadata or {}).get(b"unit", b"").decode() for f in table.schema}
        smeta = table.schema.metadata or {}
        about = json.loads(smeta.get(b"napari_unwind", b"{}"))
        unit = smeta.get(b"unit", b"").decode() or None
        return Profile(columns=cols, units=units, unit=unit, meta=dict(about.get("meta", {})))
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows or not rows[0] or rows[0][0].split(" [")[0] != "s":
        raise InvalidInputError(f"{path} is no profile: its first column is not the arc length s")
    names, units = [], {}
    for h in rows[0]:
        m = re.fullmatch(r"(.*) \[(.*)\]", h)
        name, unit = (m.group(1), m.group(2)) if m else (h, "")
        names.append(name)
        units[name] = unit
    values = np.array([[float(x) if x else np.nan for x in r] for r in rows[1:]], dtype=np.float64)
    values = values.reshape(len(rows) - 1, len(names))
    cols = {n: values[:, i].copy() for i, n in enumerate(names)}
    return Profile(columns=cols, units=units, unit=units.get("s") or None)


def _need(module: str, extra: str, what: str) -> Any:
    """Import an optional dependency, or a one-line error naming the extra that installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        from .errors import UnwindError

        raise UnwindError(f"{what} needs {top}, which is not installed: pip install napari-unwind[{extra}]") from None


#: The plot's look: small type that stays legible in the dock's ~380 px and in an 800 px PNG.
_PLOT_STYLE = {"font.size": 9, "axes.titlesize": 9, "axes.labelsize": 9, "legend.fontsize": 8,
               "xtick.labelsize": 8, "ytick.labelsize": 8, "axes.grid": True, "grid.alpha": 0.3,
               "lines.linewidth": 1.3, "legend.frameon": False}


def _channel_names(names: Sequence[str]) -> list[str]:
    """Channels of a profile: ``NAME`` with ``NAME_mean``, ``NAME_std``, ``NAME_min`` and ``NAME_max``."""
    present = set(names)
    return [n[:-5] for n in names if n.endswith("_mean")
            and all(f"{n[:-5]}_{w}" in present for w in ("std", "min", "max"))]


def _plot_panels(profile: Profile, columns: Iterable[str] | None) -> list[tuple[str, list[str], list[str]]]:
    """The panels to draw: (key, left-axis columns, right-axis columns), those with a column present only."""
    names = [n for n in profile.names if n != "s"]
    chans = _channel_names(names)
    labels = [n for n in names if n.startswith("area_label_")]
    groups = [("curvature", ["curvature", "torsion"], []), ("twist", ["twist"], []),
              ("area", ["area"], ["radius"]), ("axes", ["major_axis", "minor_axis"], ["eccentricity"]),
              ("channels", [f"{c}_mean" for c in chans], []), ("labels", labels, [])]
    if columns is None:
        wanted = None
    else:
        wanted = [str(c) for c in ([columns] if isinstance(columns, str) else columns)]
        missing = [c for c in wanted if c not in profile.columns or c == "s"]
        if missing or not wanted:
            raise InvalidInputError(f"no column {', '.join(map(repr, missing)) or 'given'} to plot; the profile has "
                                    f"{', '.join(names)}")
    panels = []
    for key, left, right in groups:
        left = [c for c in left if c in profile.columns and (wanted is None or c in wanted)]
        right = [c for c in right if c in profile.columns and (wanted is None or c in wanted)]
        if left or right:
            panels.append((key, left or right, right if left else []))
    placed = {c for _, left, right in panels for c in left + right}
    for c in wanted or ():  # columns of no group: a panel per unit
        if c not in placed:
            key = f"unit:{profile.units.get(c, '')}"
            panel = next((p for p in panels if p[0] == key), None)
            if panel is None:
                panels.append((key, [c], []))
            else:
                panel[1].append(c)
            placed.add(c)
    if not panels:
        raise InvalidInputError("the profile has no column to plot (curvature, twist, area, ...)")
    return panels


def _ylabel(profile: Profile, columns: list[str], key: str) -> str:
    if key == "channels":
        return f"{columns[0][:-5]} mean +- std" if len(columns) == 1 else "mean intensity (+- std)"
    if key == "labels":
        text = "label area"
    elif len(columns) == 1:
        text = columns[0].replace("_", " ")
    else:
        text = ", ".join(c.replace("_axis", "").replace("_", " ") for c in columns)
        text += " axis" if key == "axes" else ""
    units = {profile.units.get(c, "") for c in columns}
    unit = units.pop() if len(units) == 1 else ""
    return f"{text} [{unit}]" if unit else text


def _legend_name(column: str) -> str:
    if column.startswith("area_label_"):
        return f"label {column[len('area_label_'):]}"
    if column.endswith("_mean"):
        return column[:-5]
    return column.replace("_", " ")


def _draw_panels(figure: Any, profile: Profile, panels: list[tuple[str, list[str], list[str]]]) -> None:
    s = np.asarray(profile.columns["s"], dtype=float)
    axes = figure.subplots(len(panels), 1, sharex=True, squeeze=False)[:, 0]
    colours = [f"C{i}" for i in range(10)]
    for ax, (key, left, right) in zip(axes, panels, strict=True):
        handles = []
        for i, c in enumerate(left):
            y = np.asarray(profile.columns[c], dtype=float)
            colour = colours[i % len(colours)]
            (line,) = ax.plot(s, y, color=colour, label=_legend_name(c), gid=c)
            handles.append(line)
            std = profile.columns.get(c[:-5] + "_std") if key == "channels" else None
            if std is not None:
                ax.fill_between(s, y - std, y + std, color=colour, alpha=0.2, linewidth=0)
        ax.set_ylabel(_ylabel(profile, left, key))
        if right:
            twin = ax.twinx()
            twin.grid(False)
            for j, c in enumerate(right):
                colour = colours[(len(left) + j) % len(colours)]
                (line,) = twin.plot(s, np.asarray(profile.columns[c], dtype=float), color=colour, linestyle="--",
                                    label=_legend_name(c), gid=c)
                handles.append(line)
            twin.set_ylabel(_ylabel(profile, right, key), color=colours[len(left) % len(colours)])
        if len(handles) > 1 and len(handles) <= 12:
            ncols = min(len(handles), max(1, int(figure.get_figwidth() // 1.3)))  # 6 in the PNG, 2 in the dock
            # above the panel, clear of the curves
            (twin if right else ax).legend(handles=handles, loc="lower left", bbox_to_anchor=(0.0, 1.0),
                                           ncols=ncols, borderaxespad=0.1, handlelength=1.5, columnspacing=1.0)
    unit = profile.units.get("s", "")
    axes[-1].set_xlabel(f"arc length s [{unit}]" if unit else "arc length s")
    if len(s):
        axes[-1].set_xlim(float(s[0]), float(s[-1]))


def _unit(unit: str | None, power: int = 1) -> str:
    from .io._volume import unit_label

    u = unit_label(unit) if unit else "voxel"
    return u if power == 1 else (f"{u}^{power}" if power > 0 else f"1/{u}")


def _rotvec_about_n(frames: np.ndarray) -> np.ndarray:
    """Signed rotation (radians) about the tangent between consecutive frames (rows u, v, n), shape (K - 1,)."""
    from scipy.spatial.transform import Rotation

    r = Rotation.from_matrix(frames.transpose(0, 2, 1))         # columns u, v, n
    rel = (r[:-1].inv() * r[1:]).as_rotvec()                     # in the first frame's coordinates
    return rel[:, 2]                                             # the component about its n


#: Torsion is left empty where the radius of curvature is more than this many specimen lengths (locally straight).
STRAIGHT_RADIUS_LENGTHS = 4.0
#: ... or where the curvature is below this fraction of its median along the curve (an inflection of a bent curve).
STRAIGHT_MEDIAN_FRACTION = 0.5


def curve_geometry(deformation: Deformation, s: np.ndarray) -> dict[str, np.ndarray]:
    """Curvature, torsion and the frames' twist of a deformation at arc lengths ``s``.

    Parameters
    ----------
    deformation : Deformation
    s : ndarray, shape (K,)
        Increasing arc lengths in ``[0, L]``.

    Returns
    -------
    dict
        ``"curvature"``, ``"torsion"`` (1/length, of a not-a-knot cubic spline through the keyframe positions at
        their arc lengths; a deformation of two or three keyframes is a straight line or a parabola there; torsion
        is NaN where the curve is locally straight: its radius of curvature more than
        :data:`STRAIGHT_RADIUS_LENGTHS` times the curve's length, or its curvature below
        :data:`STRAIGHT_MEDIAN_FRACTION` of the median curvature (an inflection): there it is undefined),
        ``"twist"`` (degrees, the frames' roll about the tangent cumulated from the first station) and
        ``"twist_rate"`` (degrees per length), each shape (K,).
    """
    from scipy.interpolate import CubicSpline

    s = np.asarray(s, dtype=float)
    knots, pos = deformation.knots, deformation.positions
    if len(knots) >= 4:
        spline = CubicSpline(knots, pos, axis=0, bc_type="not-a-knot")
        d1, d2, d3 = spline(s, 1), spline(s, 2), spline(s, 3)
    else:  # a line (2) or a parabola (3) through the keyframes
        deg = len(knots) - 1
        coef = [np.polyfit(knots, pos[:, a], deg) for a in range(3)]
        d1, d2, d3 = (np.stack([np.polyval(np.polyder(c, m), s) for c in coef], axis=1) for m in (1, 2, 3))
    cross = np.cross(d1, d2)
    speed = np.linalg.norm(d1, axis=1)
    cn = np.linalg.norm(cross, axis=1)
    curvature = cn / np.maximum(speed, 1e-12) ** 3
    # torsion is undefined where the curve is straight (an inflection, a straight stretch) and near there the
    # keyframes' noise in the spline's third derivative, divided by a vanishing curvature, gives spikes of any
    # size: not reported (NaN, an empty cell) where the radius of curvature exceeds STRAIGHT_RADIUS_LENGTHS lengths
    # of the curve, or the curvature is below STRAIGHT_MEDIAN_FRACTION of its median along the curve
    length = float(knots[-1] - knots[0]) if len(knots) > 1 else 0.0
    floor = max(1.0 / (STRAIGHT_RADIUS_LENGTHS * max(length, 1e-300)),
                STRAIGHT_MEDIAN_FRACTION * float(np.median(curvature)) if len(curvature) else 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        torsion = np.where(curvature > floor,
                           np.einsum("ij,ij->i", cross, d3) / np.maximum(cn, 1e-300) ** 2, np.nan)
    _, frames = deformation.sample(s)
    if len(s) > 1:
        steps = np.degrees(_rotvec_about_n(frames))
        twist = np.concatenate([[0.0], np.cumsum(steps)])
        rate = np.gradient(twist, s) if len(s) > 2 else np.full(len(s), steps[0] / max(s[1] - s[0], 1e-12))
    else:
        twist, rate = np.zeros(1), np.zeros(1)
    return {"curvature": curvature, "torsion": torsion, "twist": twist, "twist_rate": rate}


def _section(f: np.ndarray, ds: float, grid_centre: tuple[float, float], sigma: float = 0.0,
             blur: np.ndarray | float = 0.0) -> tuple[float, ...]:
    """Area, perimeter, centroid (x, y), major, minor, eccentricity, angle of one straight slice ``f`` (y, x) of
    mask shares in [0, 1], pixels ``ds`` apart, the curve at pixel ``grid_centre`` (i0, j0); the perimeter is
    measured on ``f`` smoothed by a Gaussian of ``sigma`` pixels; ``blur`` (2 x 2, physical, x then y) is taken
    from the second moments: what the linear resampling added to them."""
    from scipy.ndimage import gaussian_filter
    from skimage.measure import find_contours

    total = float(f.sum())
    if total <= 0:
        return (0.0, 0.0) + (np.nan,) * 6
    area = total * ds * ds
    perimeter = 0.0
    pad = 1 + int(np.ceil(3 * sigma))
    padded = np.pad(f, pad)                       # closed contours where the section meets the cage's side
    if sigma > 0:
        padded = gaussian_filter(padded, sigma)
    for c in find_contours(padded, 0.5):
        perimeter += float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())
    perimeter *= ds
    ii, jj = np.indices(f.shape, dtype=float)
    ci, cj = float((f * ii).sum() / total), float((f * jj).sum() / total)
    di, dj = ii - ci, jj - cj
    mii, mjj, mij = (f * di * di).sum() / total, (f * dj * dj).sum() / total, (f * di * dj).sum() / total
    cov = np.array([[mjj, mij], [mij, mii]]) * ds * ds - blur   # (x, y), physical; less the resampling's spread
    w, vecs = np.linalg.eigh(cov)
    lo, hi = max(float(w[0]), 0.0), max(float(w[1]), 0.0)
    major, minor = 4.0 * np.sqrt(hi), 4.0 * np.sqrt(lo)
    ecc = float(np.sqrt(max(0.0, 1.0 - lo / hi))) if hi > 0 else 0.0
    vx, vy = vecs[:, 1]
    angle = float(np.degrees(np.arctan2(vy, vx)))
    angle = (angle + 90.0) % 180.0 - 90.0         # an axis, not a direction: (-90, 90]
    x0, y0 = (cj - grid_centre[1]) * ds, (ci - grid_centre[0]) * ds
    return area, perimeter, x0, y0, major, minor, ecc, angle


def _as_channels(channels: Any) -> dict[str, Any]:
    if channels is None:
        return {}
    if isinstance(channels, Mapping):
        out = {str(k): v for k, v in channels.items()}
    elif isinstance(channels, Sequence) and not isinstance(channels, (str, bytes)) and not hasattr(channels, "shape"):
        out = {f"channel{i}": v for i, v in enumerate(channels)}
    else:
        out = {"intensity": channels}
    for name in out:
        if not name or any(ch in name for ch in ",\n\r\"[]"):
            raise InvalidInputError(f"a channel name must be plain text without commas, quotes or brackets, "
                                    f"got {name!r}")
    return out


def measure_iter(
    deformation: Deformation,
    *,
    mask: Any = None,
    labels: Any = None,
    channels: Any = None,
    spacing: float | None = None,
    chunk: int = 64,
) -> Generator[Progress, None, Profile]:
    """:func:`measure` as a generator of :class:`~napari_unwind.progress.Progress`; returns the Profile."""
    from .warp import map_labels, straighten

    if not isinstance(deformation, Deformation):
        raise InvalidInputError(f"measure needs a Deformation, got {type(deformation).__name__}")
    chunk = int(chunk)
    if chunk < 1:
        raise InvalidInputError(f"chunk must be a positive number of stations, got {chunk}")
    mask, labels = _opened(mask), _opened(labels)
    chans = {name: _opened(ch) for name, ch in _as_channels(channels).items()}
    d = deformation.with_pad(0.0, 0.0)      # the stations: s = 0, ds, 2 ds, ... <= L (the padding left out)
    ds = d._ds(spacing)
    n_out, ny, nx = d.output_shape(ds)
    k0, k1 = 0, n_out - 1
    if n_out < 2:
        raise InvalidInputError(f"the deformation is shorter ({d.length:g}) than one station ({ds:g}): give a "
                                "smaller spacing")
    ks = np.arange(k0, k1 + 1)
    s = ks * ds
    unit = d.unit
    L, A, inv = _unit(unit), _unit(unit, 2), _unit(unit, -1)
    cols: dict[str, np.ndarray] = {"s": s}
    units: dict[str, str] = {"s": L}
    centres, _ = d.sample(s)
    for a in range(3):
        cols[f"centre_{a}"] = centres[:, a]
        units[f"centre_{a}"] = L
    geo = curve_geometry(d, s)
    cols.update(geo)
    units.update(curvature=inv, torsion=inv, twist="deg", twist_rate=f"deg/{L}")
    he, off = d.half_extent_at(s), d.offset_at(s)
    for name, values in (("cage_half_x", he[:, 0]), ("cage_half_y", he[:, 1]), ("cage_offset_x", off[:, 0]),
                         ("cage_offset_y", off[:, 1])):
        cols[name], units[name] = values, L

    chunks = (chunk, ny, nx)
    inputs: dict[str, Any] = {}
    if mask is not None:
        from .pipeline import specimen_mask

        mask, soft = specimen_mask(mask)  # a float map of fractional values: thresholded as every step takes it
        if soft:
            warnings.warn(soft, UserWarning, stacklevel=2)
        m = _as_array(mask)
        if m.dtype != bool and not np.issubdtype(m.dtype, np.integer) and not np.issubdtype(m.dtype, np.floating):
            raise InvalidInputError(f"the mask must be boolean, integer or float (non-zero = specimen), got {m.dtype}")
        inputs["mask"] = straighten(_on_grid(mask, m != 0, np.float32), d, order=1, spacing=ds, chunks=chunks,
                                    max_output=None).data
    if labels is not None:
        lab = _as_array(labels)
        if not np.issubdtype(lab.dtype, np.integer):
            raise InvalidInputError(f"labels must be an integer image, got {lab.dtype}")
        inputs["labels"] = map_labels(labels, d, spacing=ds, chunks=chunks, max_output=None)
    for name, ch in chans.items():
        inputs[f"channel:{name}"] = straighten(ch, d, order=1, spacing=ds, chunks=chunks, max_output=None).data
    if chans and mask is None:  # the cross-section is the cage where it samples the scan
        import dask.array as da

        first = _as_array(next(iter(chans.values())))
        inputs["mask"] = straighten(_on_grid(next(iter(chans.values())), da.ones(first.shape, chunks=64),
                                             np.float32), d, order=1, spacing=ds, chunks=chunks,
                                    max_output=None).data
    grid_centre = d.grid_centre(ds)
    # the perimeter's contour is taken on the section smoothed by half a scan voxel: the resampled binary mask is a
    # staircase, whose 0.5-contour is 3-5 % longer than the boundary it samples (a disk of 6 voxels)
    sigma = 0.5 * max(d.spacing) / ds
    # linear resampling spreads each scan voxel over a tent of its size: h^2 / 6 more second moment along each scan
    # axis, seen in the section through its frame (a disk of 5 voxels read 4 % wide without this)
    _, fr = d.sample(s)
    h2 = np.asarray(d.spacing) ** 2 / 6.0
    uv = fr[:, :2, :]                                            # (K, 2, 3): u and v in scan axes
    blur = np.einsum("kia,a,kja->kij", uv, h2, uv)
    sect = np.full((len(s), 8), np.nan) if mask is not None else None
    label_area: dict[int, np.ndarray] = {}
    stats = {name: np.full((len(s), 4), np.nan) for name in chans}
    n_chunks = -(-len(ks) // chunk)
    yield Progress("measure", 0, n_chunks, f"{len(s)} stations")
    import dask

    for c in range(n_chunks):
        a, b = k0 + c * chunk, min(k0 + (c + 1) * chunk, k1 + 1)
        names = list(inputs)
        blocks = dask.compute(*[inputs[n][a:b] for n in names], scheduler="threads")
        got = dict(zip(names, blocks, strict=True))
        rows = slice(a - k0, b - k0)
        fm = got.get("mask")
        if fm is not None:
            fm = np.clip(np.asarray(fm, dtype=np.float64), 0.0, 1.0)
            if sect is not None:
                sect[rows] = [_section(sl, ds, grid_centre, sigma, blur[a - k0 + i]) for i, sl in enumerate(fm)]
        if "labels" in got:
            lb = np.asarray(got["labels"])
            ids, counts = _label_counts(lb)
            for i, row in zip(*np.nonzero(counts), strict=True):
                label = int(ids[row])
                label_area.setdefault(label, np.zeros(len(s)))[a - k0 + i] = counts[i, row] * ds * ds
            if len(label_area) > MAX_LABELS:
                raise InvalidInputError(f"the label image has more than {MAX_LABELS} labels along the specimen; "
                                        "give a label image of the parts to measure")
        for name in chans:
            v = np.asarray(got[f"channel:{name}"], dtype=np.float64)
            inside = fm >= 0.5
            for i in range(v.shape[0]):
                vals = v[i][inside[i]]
                if vals.size:
                    stats[name][a - k0 + i] = (vals.mean(), vals.std(), vals.min(), vals.max())
        yield Progress("measure", c + 1, n_chunks)
    if sect is not None:
        for j, (name, u) in enumerate((("area", A), ("perimeter", L), ("centroid_x", L), ("centroid_y", L),
                                       ("major_axis", L), ("minor_axis", L), ("eccentricity", ""),
                                       ("major_angle", "deg"))):
            cols[name], units[name] = sect[:, j], u
            if name == "perimeter":
                cols["radius"], units["radius"] = np.sqrt(sect[:, 0] / np.pi), L
    for label in sorted(label_area):
        cols[f"area_label_{label}"], units[f"area_label_{label}"] = label_area[label], A
    for name, st in stats.items():
        for j, what in enumerate(("mean", "std", "min", "max")):
            cols[f"{name}_{what}"], units[f"{name}_{what}"] = st[:, j], ""
    return Profile(columns=cols, units=units, unit=unit)


def measure(deformation: Deformation, *, mask: Any = None, labels: Any = None, channels: Any = None,
            spacing: float | None = None, chunk: int = 64, progress: Any = None) -> Profile:
    """Measure a specimen along its deformation's centreline.

    Parameters
    ----------
    deformation : Deformation
        The centreline, its frames and cage.
    mask : array-like or Volume, shape (N0, N1, N2), optional
        The specimen on the deformation's scan grid (non-zero inside): gives the cross-section columns.
    labels : integer array-like or Volume, shape (N0, N1, N2), optional
        A label image on the same grid: one area column per label met along the specimen (at most
        :data:`MAX_LABELS`).
    channels : array-like, Volume, list or dict of them, optional
        Intensity images on the same grid (a dict names them; a list is ``channel0, channel1, ...``; a single
        image is ``intensity``): mean, std, min and max per station over the cross-section (inside the mask when
        given).
    spacing : float, optional
        Station spacing and the cross-sections' pixel size (physical units); default the finest scan spacing.
    chunk : int
        Stations computed together (bounds memory: one chunk of the straight volume per input).
    progress : callable, optional
        Called with each :class:`~napari_unwind.progress.Progress`.

    Returns
    -------
    Profile
        One row per station ``s`` in ``[0, L]``, ``spacing`` apart.

    Raises
    ------
    InvalidInputError
        For inputs off the deformation's grid (their geometry is compared as in
        :func:`~napari_unwind.warp.straighten`), a mask or labels of the wrong type, too many labels.
    """
    return run_with_progress(measure_iter(deformation, mask=mask, labels=labels, channels=channels,
                                          spacing=spacing, chunk=chunk), progress)


def _opened(value: Any) -> Any:
    """A path opened as a Volume (once); anything else as it is."""
    if isinstance(value, (str, os.PathLike)):
        from .io import open_volume

        return open_volume(value)
    return value


def _as_array(value: Any) -> Any:
    from .io import Volume

    data = value.data if isinstance(value, Volume) else value
    if not hasattr(data, "dtype"):
        data = np.asarray(data)
    return data


def _on_grid(original: Any, data: Any, dtype: Any) -> Any:
    """``data`` (derived from ``original``'s voxels) with ``original``'s geometry when it is a Volume."""
    from .io import Volume

    data = data.astype(dtype)
    if isinstance(original, Volume):
        return Volume(data, spacing=original.spacing, origin=original.origin, unit=original.unit)
    return data


def _label_counts(lb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Labels present in a block (without 0) and their pixel count per slice, shape (n_slices, n_labels)."""
    ids = np.unique(lb)
    ids = ids[ids != 0]
    if ids.size == 0:
        return ids, np.zeros((lb.shape[0], 0), dtype=np.int64)
    idx = np.searchsorted(ids, lb)
    idx = np.where(lb == 0, len(ids), np.clip(idx, 0, len(ids)))
    counts = np.zeros((lb.shape[0], len(ids) + 1), dtype=np.int64)
    for i in range(lb.shape[0]):
        counts[i] = np.bincount(idx[i].ravel(), minlength=len(ids) + 1)
    return ids, counts[:, :-1]
