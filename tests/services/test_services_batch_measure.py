"""``Client.run_batch(..., measure=True)`` (issue 24 item 4): each specimen's row gains the summary of its profile
along the centreline, and those figures are the ones of :func:`napari_unwind.measure.measure` run in this process
on the same session and the same mask (the mask refined here from the scan, as the pipeline does), summarised here
with numpy."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from _servers import ServerProcess

from napari_unwind.client import BatchItem, Client, profile_summary
from napari_unwind.datasets import tank_phantom
from napari_unwind.deformation import Deformation
from napari_unwind.errors import InvalidInputError
from napari_unwind.io import open_volume, write_volume


def test_a_measured_batch_has_the_local_profiles_summary(tmp_path):
    from napari_unwind.measure import measure
    from napari_unwind.segmentation import join_tree, refine_mask, select

    t = tank_phantom(n_fish=1, seed=2, length=80)
    scan = write_volume(t.volume, tmp_path / "tank.zarr", spacing=t.spacing, unit=t.unit)
    fish = t.fish[0]
    click = fish.centerline[len(fish.centerline) // 2]
    srv = ServerProcess(tmp_path / "data", "--workers", "2")
    try:
        with Client(srv.address, progress=False) as c:
            rows = c.run_batch([BatchItem(scan=str(scan), select=[click], name="fish")], out_dir=tmp_path / "out",
                               suffix=".nrrd", measure=True)
    finally:
        srv.stop()
    (row,) = rows
    assert row["state"] == "succeeded" and not row.get("measure_error"), row
    # the same session and the same mask, measured in this process
    d = Deformation.from_dict(json.loads((tmp_path / "out" / "fish.unwind.json").read_text())["deformation"])
    volume = open_volume(scan)
    features = join_tree(volume).simplify(5)
    mask = refine_mask(volume, select(features, seeds=[click]), features=features).compute()
    local = measure(d, mask=mask.astype(np.uint8))
    s, k, area = local["s"], local["curvature"], local["area"]
    unit = local.units["s"]                                      # the profile's short unit ("um")
    assert local.units["curvature"] == f"1/{unit}" and local.units["area"] == f"{unit}^2"
    want = {f"curvature_mean [1/{unit}]": np.nanmean(k),
            f"curvature_max [1/{unit}]": np.nanmax(k), f"area_mean [{unit}^2]": np.nanmean(area),
            f"area_max [{unit}^2]": np.nanmax(area), f"radius_max [{unit}]": np.sqrt(np.nanmax(area) / np.pi),
            f"volume [{unit}^3]": np.trapezoid(np.nan_to_num(area), s)}
    for name, value in want.items():
        assert float(row[name]) == pytest.approx(value, rel=1e-6), (name, row[name], value)
    assert float(row["length"]) == pytest.approx(d.length, rel=1e-5) and row["unit"]      # the pipeline's own
    # the summary CSV carries the columns, with units, after the pipeline's
    with open(tmp_path / "out" / "summary.csv") as f:
        header = next(csv.reader(f))
    assert [h for h in header if h in want] == list(want)
    assert (tmp_path / "out" / "fish.profile.csv").read_text().startswith("s [")


def test_a_summary_of_what_is_no_profile_is_refused():
    with pytest.raises(InvalidInputError, match="arc length"):
        profile_summary("a,b\n1,2\n")
    only_curve = profile_summary("s [mm],curvature [1/mm]\n0,0.1\n2,0.3\n")
    assert only_curve == {"curvature_mean [1/mm]": pytest.approx(0.2), "curvature_max [1/mm]": 0.3}
    no_radius = profile_summary("s [mm],area [mm^2]\n0,1\n2,3\n3,\n")
    assert no_radius == {"area_mean [mm^2]": 2.0, "area_max [mm^2]": 3.0, "volume [mm^3]": 4.0 + 1.5}
