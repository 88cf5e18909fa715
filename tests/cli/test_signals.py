"""SIGTERM is handled like Ctrl-C; what SIGKILL leaves behind is removed by the next run (issue 9).

The export is slowed by a fine output spacing; the signal is sent once the temporary output exists, i.e. in the
middle of writing.
"""

import signal
import subprocess
import time

import pytest
from cli_support import UNWIND, demo_outputs, error_lines, leftovers

from napari_unwind.io import open_volume


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return demo_outputs(tmp_path_factory)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_export(demo, out):
    # SIGINT back to its default in the child: a suite started as a background job of a non-interactive shell
    # inherits SIGINT ignored (POSIX), and an unwind started from it rightly ignores Ctrl-C too (it then ended
    # with 0 here, in a fresh clone's run started with `&`)
    return subprocess.Popen([str(UNWIND), "straighten", str(demo.tank), "--session", str(demo.session), "-o",
                             str(out), "--spacing", "0.2", "--no-verify", "-q"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint)


def _signal_when_writing(procs, folders, signals, timeout=120):
    """Send each process its signal as soon as its temporary output exists (all watched at once)."""
    pending = set(procs)
    t0 = time.monotonic()
    while pending and time.monotonic() - t0 < timeout:
        for name in sorted(pending):
            if leftovers(folders[name]):
                procs[name].send_signal(signals[name])
                pending.discard(name)
            elif procs[name].poll() is not None:
                pytest.fail(f"the {name} export ended before it was signalled: {procs[name].communicate()}")
        time.sleep(0.01)
    for name in pending:
        procs[name].kill()
    assert not pending, f"no temporary output appeared for {sorted(pending)}"


def test_signals_mid_export(demo, tmp_path):
    """SIGTERM and SIGINT: nothing left, one line, 143 and 130. SIGKILL: the next run removes what is left.

    The three exports run at once (the interpreter's start is paid once in wall time).
    """
    folders = {name: tmp_path / name for name in ("term", "int", "kill")}
    procs = {}
    for name, folder in folders.items():
        folder.mkdir()
        procs[name] = _start_export(demo, folder / "straight.zarr")
    signals = {"term": signal.SIGTERM, "int": signal.SIGINT, "kill": signal.SIGKILL}
    _signal_when_writing(procs, folders, signals)
    errs = {name: p.communicate(timeout=60)[1] for name, p in procs.items()}
    time.sleep(0.5)  # nothing reappears once the processes have gone
    for name, status, says in (("term", 143, "terminated (SIGTERM)"), ("int", 130, "interrupted")):
        assert procs[name].returncode == status, errs[name]
        assert error_lines(errs[name]) == [f"unwind: {says}; no partial output was left behind"], errs[name]
        assert leftovers(folders[name]) == [] and not (folders[name] / "straight.zarr").exists()
    # SIGKILL cannot be handled: its temporary output stays, named after the dead process...
    kill = procs["kill"]
    assert kill.returncode == -signal.SIGKILL
    stale = [p for p in leftovers(folders["kill"]) if p.parent == folders["kill"]]
    assert stale and all(f".p{kill.pid}." in p.name for p in stale)
    # ...and the next run to the same output removes it
    out = folders["kill"] / "straight.zarr"
    r = subprocess.run([str(UNWIND), "straighten", str(demo.tank), "--session", str(demo.session), "-o", str(out),
                        "--no-verify", "-q"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert leftovers(folders["kill"]) == []
    assert open_volume(out).shape[0] > 100
