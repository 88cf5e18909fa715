"""The Average job on a real server (issue 24 items 3-4): the same bytes as :func:`napari_unwind.average.average`
in this process for the same volumes and options (the servicer adds nothing), and bad requests refused with the
right status: options INVALID_ARGUMENT (at Submit, or as the job runs when they need the volumes), an unknown
volume NOT_FOUND."""

from __future__ import annotations

import csv
import io
import sys
from pathlib import Path

import numpy as np
import pytest
from _servers import ServerProcess

from napari_unwind.average import average
from napari_unwind.client import Client, RemoteError
from napari_unwind.pipeline import _write_table

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import test_average as fam  # noqa: E402


@pytest.fixture(scope="module")
def batch(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("average_server")
    rng = np.random.default_rng(7)
    old = fam.NS0, fam.NY0
    fam.NS0, fam.NY0 = 50, 21
    try:
        members = [fam.member(z, th, rng.uniform(-2, 2, 2), rng.uniform(0.5, 2), rng.uniform(0, 200), rng)
                   for z, th in [(0.9, -20.0), (1.0, 0.0), (1.1, 15.0), (0.95, 30.0)]]
    finally:
        fam.NS0, fam.NY0 = old
    srv = ServerProcess(tmp / "data", "--workers", "1")
    yield tmp, members, srv
    srv.stop()


def test_the_servers_average_is_the_local_one_byte_for_byte(batch, tmp_path):
    _, members, srv = batch
    with Client(srv.address, progress=False) as c:
        ids = [c.upload(m, name=f"fish{i}.zarr").volume_id for i, m in enumerate(members)]
        job = c.average(ids, output_name="fishes.ome.zarr")
        names = [r["name"] for r in csv.DictReader(io.StringIO(job.result.table_csv))]
        local = average(members, names=names)
        assert set(job.result.volumes) == {"mean", "median", "std"}
        assert job.result.volume_id == job.result.volumes["mean"]
        for what in ("mean", "median", "std"):
            got = c.open(job.result.volumes[what])
            want = getattr(local, what)
            assert got.data.dtype == want.dtype and got.spacing == (local.spacing,) * 3 and got.unit == local.unit
            np.testing.assert_array_equal(got.data.compute(), want, err_msg=what)
        # the residuals: the bytes unwind average writes beside the mean
        rows = local.table()
        _write_table(rows, tmp_path / "residuals.csv", list(rows[0]))
        assert job.result.table_csv == (tmp_path / "residuals.csv").read_text()
        assert names == [f"fish{i}.zarr" for i in range(4)]
        # other options, landmarks among them: still the local result
        lm = [[0.4 * (m.shape[0] - 1) * 0.5] for m in members]
        job = c.average(ids, landmarks=lm, scale="none", normalise="none", max_roll=0.0, stations=40)
        local = average(members, landmarks=lm, scale="none", normalise="none", max_roll=0.0, stations=40)
        np.testing.assert_array_equal(c.open(job.result.volume_id).data.compute(), local.mean)

        def refused(**kw):
            with pytest.raises(RemoteError) as err:
                c.average(kw.pop("volume_ids", ids), **kw)
            return err.value.code, str(err.value)

        assert refused(volume_ids=ids[:1])[0] == "INVALID_ARGUMENT"
        assert refused(volume_ids=[ids[0], ids[0]])[0] == "INVALID_ARGUMENT"
        assert refused(max_roll=200.0)[0] == "INVALID_ARGUMENT"
        assert refused(landmarks=[[1.0], [1.0], [1.0], [1.0, 2.0]])[0] == "INVALID_ARGUMENT"
        code, msg = refused(landmarks=[[1.0], [1.0], [1.0], [1e6]])          # beyond the specimen: as the job runs
        assert code == "INVALID_ARGUMENT" and "inside its length" in msg, msg
        assert refused(volume_ids=[ids[0], "v_nothere"])[0] == "NOT_FOUND"
        assert refused(output_name="mean.xyz")[0] == "INVALID_ARGUMENT"
