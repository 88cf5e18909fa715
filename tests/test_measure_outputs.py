"""The profile's outputs (issue 24 item 2): Parquet with its units, the PNG plot, ``unwind measure -o x.parquet
--plot p.png``, and the readers.

References: the in-memory profile (the values a writer must keep), pyarrow's own reader (not
:func:`~napari_unwind.measure.read_profile`) for what a Parquet file holds, matplotlib's PNG reader for the picture's
size, and :func:`~napari_unwind.measure.measure` called directly for what the command line writes.
"""

from __future__ import annotations

import sys

import numpy as np
import pytest

from conftest import no_leftovers
from conftest import run_unwind as _run
from napari_unwind.errors import InvalidInputError, UnwindError
from napari_unwind.measure import Profile, measure, read_profile

pa = pytest.importorskip("pyarrow")
pq = pytest.importorskip("pyarrow.parquet")
pytest.importorskip("matplotlib")


def profile(*, mask=True, labels=(), channels=()):
    """A profile as measure() builds it (names and units), with values chosen here; a gap (NaN) in the area."""
    s = np.arange(0.0, 10.01, 0.5)
    cols = {"s": s, "curvature": 0.1 + 0.01 * s, "torsion": -0.02 * np.ones_like(s), "twist": 9.0 * s,
            "twist_rate": 9.0 * np.ones_like(s)}
    units = {"s": "mm", "curvature": "1/mm", "torsion": "1/mm", "twist": "deg", "twist_rate": "deg/mm"}
    if mask:
        area = np.pi * (1 + np.sin(s)) ** 2
        area[3] = np.nan
        cols.update(area=area, perimeter=2 * np.pi * (1 + np.sin(s)), radius=np.sqrt(area / np.pi),
                    major_axis=4 + s, minor_axis=2 + 0 * s, eccentricity=np.sqrt(1 - (2 / (4 + s)) ** 2))
        units.update(area="mm^2", perimeter="mm", radius="mm", major_axis="mm", minor_axis="mm", eccentricity="")
    for lab in labels:
        cols[f"area_label_{lab}"] = lab * s
        units[f"area_label_{lab}"] = "mm^2"
    for name in channels:
        for j, what in enumerate(("mean", "std", "min", "max")):
            cols[f"{name}_{what}"] = 100.0 * (j + 1) + s
            units[f"{name}_{what}"] = ""
    return Profile(columns=cols, units=units, unit="millimeter", meta={"session": "fish.unwind.json"})


# ---- Parquet ---------------------------------------------------------------------------------------------------------
def test_parquet_holds_the_values_units_and_provenance_and_repeats_its_bytes(tmp_path):
    p = profile(labels=(3,), channels=("scan",))
    path = p.to_parquet(tmp_path / "a.parquet")
    table = pq.read_table(path)                              # pyarrow's own reader
    assert table.column_names == p.names
    for f in table.schema:
        assert f.type == pa.float64()
        assert f.metadata[b"unit"].decode() == p.units[f.name], f.name
        got = np.asarray(table.column(f.name).to_numpy(zero_copy_only=False), dtype=float)
        np.testing.assert_array_equal(got, p[f.name])         # float64 kept exactly; the gap NaN
    assert table.column("area").null_count == 1 and not table.column("area").is_valid()[3].as_py()
    meta = table.schema.metadata
    assert meta[b"unit"] == b"millimeter"
    assert b'"session": "fish.unwind.json"' in meta[b"napari_unwind"]
    again = p.to_parquet(tmp_path / "b.parquet")
    assert path.read_bytes() == again.read_bytes()
    with pytest.raises(UnwindError, match="exists"):
        p.to_parquet(path)
    back = read_profile(path)
    assert back.names == p.names and back.units == p.units and back.unit == "millimeter" and back.meta == p.meta
    for n in p.names:
        np.testing.assert_array_equal(back[n], p[n])
    assert no_leftovers(tmp_path) == []


def test_without_pyarrow_a_one_line_error_names_the_extra(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyarrow", None)         # import pyarrow now raises ImportError
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)
    with pytest.raises(UnwindError) as err:
        profile().to_parquet(tmp_path / "a.parquet")
    assert "pip install napari-unwind[tables]" in str(err.value) and "\n" not in str(err.value)
    assert list(tmp_path.iterdir()) == []


def test_the_csv_reads_back_to_the_profile_within_its_nine_digits(tmp_path):
    p = profile(labels=(1, 2), channels=("gfp",))
    back = read_profile(p.to_csv(tmp_path / "a.csv"))
    assert back.names == p.names and back.units == p.units and back.unit == "mm"
    for n in p.names:
        np.testing.assert_allclose(back[n], p[n], rtol=5e-9, atol=0, equal_nan=True)
    assert np.isnan(back["area"][3])
    with pytest.raises(InvalidInputError, match=r"\.csv or \.parquet"):
        read_profile(tmp_path / "a.xlsx")


def test_save_picks_the_format_by_suffix_and_refuses_others(tmp_path):
    p = profile()
    assert p.save(tmp_path / "a.csv").read_text().startswith("s [mm],curvature [1/mm]")
    assert p.save(tmp_path / "a.Parquet").read_bytes()[:4] == b"PAR1"
    assert p.save(tmp_path / "a.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(InvalidInputError) as err:
        p.save(tmp_path / "a.xlsx")
    assert all(s in str(err.value) for s in (".csv", ".parquet", ".png", "a.xlsx"))
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.Parquet", "a.csv", "a.png"]


# ---- the plot --------------------------------------------------------------------------------------------------------
def curves(fig):
    """Column name -> (x, y) of every curve of a figure (each curve's gid is its column)."""
    return {line.get_gid(): (line.get_xdata(), line.get_ydata())
            for ax in fig.axes for line in ax.get_lines() if line.get_gid()}


def test_the_plot_draws_each_column_against_s_one_panel_per_group_with_units(tmp_path):
    import matplotlib.image

    p = profile(labels=(1, 7), channels=("scan",))
    fig = p.plot(tmp_path / "a.png")
    drawn = curves(fig)
    assert set(drawn) == {"curvature", "torsion", "twist", "area", "radius", "major_axis", "minor_axis",
                          "eccentricity", "scan_mean", "area_label_1", "area_label_7"}
    for name, (x, y) in drawn.items():
        np.testing.assert_array_equal(x, p["s"])
        np.testing.assert_array_equal(y, p[name])
    labels = [ax.get_ylabel() for ax in fig.axes]
    assert "curvature, torsion [1/mm]" in labels and "twist [deg]" in labels and "area [mm^2]" in labels
    assert "radius [mm]" in labels and "major, minor axis [mm]" in labels and "eccentricity" in labels
    assert "label area [mm^2]" in labels and "scan mean +- std" in labels
    assert fig.axes[5].get_xlabel() == "arc length s [mm]"
    assert len({round(ax.get_position().y0, 6) for ax in fig.axes}) == 6   # six panels (a twin shares its host's)
    image = matplotlib.image.imread(tmp_path / "a.png")
    assert image.shape[:2] == (round((0.9 + 1.9 * 6) * 100), 800)
    assert p.plot(tmp_path / "b.png") is not None
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()


def test_the_plot_has_only_the_panels_present_and_the_columns_asked_for(tmp_path):
    p = profile(mask=False)
    fig = p.plot()
    assert set(curves(fig)) == {"curvature", "torsion", "twist"}
    assert sum(1 for ax in fig.axes if ax.get_lines()) == 2
    fig = profile().plot(columns=["radius", "perimeter", "twist_rate"])
    drawn = curves(fig)
    assert set(drawn) == {"radius", "perimeter", "twist_rate"}
    assert {ax.get_ylabel() for ax in fig.axes if ax.get_lines()} == {"radius [mm]", "perimeter [mm]",
                                                                       "twist rate [deg/mm]"}
    with pytest.raises(InvalidInputError, match="no column 'volume'"):
        p.plot(columns=["volume"])
    with pytest.raises(InvalidInputError, match=r"ending in \.png"):
        p.plot(tmp_path / "a.jpg")
    assert list(tmp_path.iterdir()) == []


# ---- the command line ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def case(tmp_path_factory):
    from napari_unwind.datasets import fish_phantom
    from napari_unwind.demo import true_deformation
    from napari_unwind.io import write_volume
    from napari_unwind.session import Session, SourceInfo, save_session

    tmp = tmp_path_factory.mktemp("measure_outputs")
    fish = fish_phantom(length=80, body_radius=5, tube=False, seed=1, noise=0.0)
    scan = write_volume(fish.volume, tmp / "fish.nrrd", spacing=fish.spacing, unit=fish.unit)
    mask = write_volume(fish.mask.astype(np.uint8), tmp / "mask.nrrd", spacing=fish.spacing, unit=fish.unit)
    d = true_deformation(fish)
    session = save_session(Session(source=SourceInfo.from_path(scan), deformation=d), tmp / "fish.unwind.json")
    return tmp, scan, mask, session, d


def test_unwind_measure_writes_parquet_and_the_plot(case):
    from napari_unwind.io import open_volume

    tmp, scan, mask, session, d = case
    out, png = tmp / "profile.parquet", tmp / "profile.png"
    code, stdout, err = _run("measure", "--session", session, "--mask", mask, "--channel", f"scan={scan}",
                             "-o", out, "--plot", png, "-q")
    assert code == 0, err
    direct = measure(d, mask=open_volume(mask), channels={"scan": open_volume(scan)})
    table = pq.read_table(out)
    assert table.column_names == direct.names
    for f in table.schema:
        assert f.metadata[b"unit"].decode() == direct.units[f.name]
        got = np.asarray(table.column(f.name).to_numpy(zero_copy_only=False), dtype=float)
        np.testing.assert_array_equal(got, np.where(np.isfinite(direct[f.name]), direct[f.name], np.nan))
    assert table.schema.field("s").metadata[b"unit"] in (b"um", "µm".encode())
    assert table.schema.metadata[b"unit"] == b"micrometer"
    assert b"fish.unwind.json" in table.schema.metadata[b"napari_unwind"]
    direct.plot(tmp / "direct.png")
    assert png.read_bytes() == (tmp / "direct.png").read_bytes()   # the same profile, the same picture
    assert no_leftovers(tmp) == []


def test_unwind_measure_refuses_other_suffixes_in_one_line(case, capsys):
    from napari_unwind.cli import main

    tmp, scan, mask, session, d = case
    code = main(["measure", "--session", str(session), "--mask", str(mask), "-o", str(tmp / "p.xlsx"), "-q"])
    err = capsys.readouterr().err
    assert code != 0 and ".csv" in err and ".parquet" in err and len(err.strip().splitlines()) == 1
    code = main(["measure", "--session", str(session), "--mask", str(mask), "-o", str(tmp / "p.csv"), "--plot",
                 str(tmp / "p.jpg"), "-q"])
    err = capsys.readouterr().err
    assert code != 0 and ".png" in err and len(err.strip().splitlines()) == 1
    assert not (tmp / "p.csv").exists() and not (tmp / "p.xlsx").exists() and not (tmp / "p.jpg").exists()


def test_unwind_measure_without_pyarrow_says_which_extra(case, monkeypatch, capsys):
    from napari_unwind.cli import main

    tmp, scan, mask, session, d = case
    monkeypatch.setitem(sys.modules, "pyarrow", None)
    code = main(["measure", "--session", str(session), "--mask", str(mask), "-o", str(tmp / "q.parquet"), "-q"])
    err = capsys.readouterr().err
    assert code != 0 and "pip install napari-unwind[tables]" in err and len(err.strip().splitlines()) == 1
    assert not (tmp / "q.parquet").exists()
