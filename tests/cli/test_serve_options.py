"""`unwind serve`'s numbers that lie (issue 20): a port past 65535 (gRPC listened on a port of its own choosing)
and a token's expiry that is not a positive, finite number of days (inf gave a traceback)."""

from __future__ import annotations

import pytest

from napari_unwind.cli import main


@pytest.mark.parametrize("args, says", [
    (["--port", "99999"], "a port is a whole number in 0..65535 (0: any free port), got '99999'"),
    (["--port", "65536"], "got '65536'"),
    (["--port", "-1"], "expected a whole number >= 0, got '-1'"),
    (["--add-token", "bob", "--expires-days", "inf"], "expected a number of days in (0, 36500], got 'inf'"),
    (["--add-token", "bob", "--expires-days", "nan"], "got 'nan'"),
    (["--add-token", "bob", "--expires-days", "0"], "got '0'"),
    (["--add-token", "bob", "--expires-days", "1e400"], "got '1e400'"),
])
def test_serve_refuses_numbers_no_server_can_use_in_one_line(tmp_path, capsys, args, says):
    code = main(["serve", "--data", str(tmp_path), *args])
    err = capsys.readouterr().err
    assert code == 1 and err.count("\n") == 1 and says in err and "Traceback" not in err, err
    assert list(tmp_path.iterdir()) == []  # nothing made in the data root


def test_the_ports_at_the_ends_of_the_range_are_taken():
    from napari_unwind._cli_remote import _port

    assert _port("0") == 0 and _port("65535") == 65535
