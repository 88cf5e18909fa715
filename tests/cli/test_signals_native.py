"""Signals after and inside compiled code (issue 20, item 6).

fTetWild's first call in a process resets the C-level SIGINT handler to SIG_DFL behind Python's back (geogram's
initialisation calls ``signal(SIGINT, SIG_DFL)``): a later Ctrl-C then killed the process outright (status -2, no
message, the temporary output left), and during that first call any thread Python did not start took a SIGINT into
SIG_DFL. ``napari_unwind._compat.tetrahedralize`` now runs the mesher in a child process. The command line's own
skeleton uses the lattice mesher, so the runs here use a child that makes the pipeline's skeleton solve mesh with
fTetWild (``tet_mesher="ftetwild"``, the library's option), then
signal the run once its export has begun (its temporary output exists), i.e. after the solve.

Each child is a fresh process: fTetWild resets the handler on its first call only.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from cli_support import demo_outputs, error_lines, leftovers

# the pipeline's skeleton solve with fTetWild, then the command line; prints one line when fTetWild has run
FTETWILD_CLI = textwrap.dedent("""
    import sys
    from napari_unwind import _compat, pipeline
    from napari_unwind.cli import main

    kwargs = pipeline.SkeletonOptions.kwargs
    pipeline.SkeletonOptions.kwargs = lambda self: {**kwargs(self), "tet_mesher": "ftetwild"}
    mesh = _compat.tetrahedralize

    def tetrahedralize(*args, **kw):
        out = mesh(*args, **kw)
        print("meshed with fTetWild", flush=True)
        return out

    _compat.tetrahedralize = tetrahedralize
    sys.argv[0] = "unwind"
    sys.exit(main())  # as the command does (argv from sys.argv)
""")

SAYS = {signal.SIGINT: (130, "interrupted"), signal.SIGTERM: (143, "terminated (SIGTERM)")}


def _default_sigint() -> None:
    # a suite started in the background of a non-interactive shell passes SIGINT on ignored (see test_signals)
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(code: str, *args, cwd: Path | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", code, *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=cwd, preexec_fn=_default_sigint,
                            env={**os.environ, "PYTHONWARNINGS": ""})


def _when(procs: dict, ready, timeout: float = 240) -> None:
    """Wait until ``ready(name)`` holds for every process (all watched at once), then send its signals."""
    pending = dict(procs)
    t0 = time.monotonic()
    while pending and time.monotonic() - t0 < timeout:
        for name in sorted(pending):
            proc, signals = pending[name]
            if ready(name):
                for s in signals:
                    proc.send_signal(s)
                del pending[name]
            elif proc.poll() is not None:
                pytest.fail(f"{name} ended before it was signalled: {proc.communicate()}")
        time.sleep(0.01)  # polling the condition, not a wait for it
    for proc, _ in pending.values():
        proc.kill()
    assert not pending, f"never ready: {sorted(pending)}"


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    return demo_outputs(tmp_path_factory)


def test_run_signalled_after_ftetwild(demo, tmp_path):
    """SIGINT once, SIGTERM three times, each once the export of a run whose skeleton was meshed by fTetWild has
    begun, and SIGTERM then, once its temporary output is gone, SIGINT: the (first) signal's status and one line,
    no temporary output, no volume.

    Before the fix SIGINT killed the run (-2, no line, the temporary output left); a SIGINT landing while the
    interpreter shut down after a SIGTERM killed it too (-2). Signals sent together coalesce (a signal number is
    pending once) and are handled in signal-number order (two different ones: SIGINT first), hence the wait for
    the cleanup before the second one; test_second_signal_during_cleanup_is_ignored lands one inside it."""
    cases = {"int": [signal.SIGINT], "term3": [signal.SIGTERM] * 3, "term-then-int": [signal.SIGTERM]}
    procs = {}
    for name, signals in cases.items():
        (tmp_path / name).mkdir()
        procs[name] = (_start(FTETWILD_CLI, "run", demo.tank, "--select", demo.point, "-o",
                              tmp_path / name / "fish.zarr", "--spacing", "0.2"), signals)
    _when(procs, lambda name: bool(leftovers(tmp_path / name)))
    # a second signal once the first was handled (its temporary output removed): ignored, whenever it lands
    _when({"term-then-int": (procs["term-then-int"][0], [signal.SIGINT])},
          lambda name: not leftovers(tmp_path / "term-then-int"))
    for name, (proc, signals) in procs.items():
        out, err = proc.communicate(timeout=120)
        status, says = SAYS[signals[0]]
        assert proc.returncode == status, (name, proc.returncode, err[-2000:])
        assert "meshed with fTetWild" in out, name
        assert error_lines(err)[-1:] == [f"unwind: {says}; no partial output was left behind"], (name, err)
        assert "Traceback" not in err and "Exception ignored" not in err, (name, err)
        assert leftovers(tmp_path / name) == [] and not (tmp_path / name / "fish.zarr").exists(), name


def test_run_all_signalled_midway(demo, tmp_path):
    """``run --all`` interrupted once its first specimen is written: 130, and no output folder at all."""
    batch = tmp_path / "batch"
    proc = _start(FTETWILD_CLI, "run", demo.tank, "--all", "-o", batch, "--spacing", "0.2")
    _when({"all": (proc, [signal.SIGINT])}, lambda name: batch.is_dir() and any(
        p.suffix == ".zarr" and "unwind-tmp" not in p.name for p in batch.iterdir()))
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err[-2000:]
    assert error_lines(err)[-1:] == ["unwind: interrupted; no partial output was left behind"], err
    assert not batch.exists(), sorted(p.name for p in batch.iterdir())
    assert leftovers(tmp_path) == []


# SIGTERM sent from inside a callback of compiled code (libc's qsort through ctypes), where an exception cannot pass:
# ctypes reports it as "ignored" and goes on
QSORT_CALLBACK = textwrap.dedent("""
    import ctypes, os, signal, sys, time
    from napari_unwind import cli

    def job(args):
        sent = []
        def compare(a, b):
            if not sent:
                sent.append(True)
                os.kill(os.getpid(), signal.SIGTERM)
            return a[0] - b[0]
        compare_c = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ctypes.c_int))
        values = (ctypes.c_int * 100)(*range(100, 0, -1))
        ctypes.CDLL(None).qsort(values, 100, ctypes.sizeof(ctypes.c_int), compare_c(compare))
        deadline = time.monotonic() + 20  # Python's own work: the interrupt must be raised again in here
        while time.monotonic() < deadline:
            pass
        print("went on for 20 s after the signal", flush=True)
        return 0

    cli.cmd_info = job
    sys.exit(cli.main(["info", "x"]))
""")


def test_sigterm_inside_compiled_callback_not_swallowed():
    """Raised again in the Python code that follows (not lost, and not only when the command returns)."""
    proc = _start(QSORT_CALLBACK)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and out == "", (proc.returncode, out, err)
    assert error_lines(err) == ["unwind: terminated (SIGTERM); no partial output was left behind"], err


# SIGTERM, then SIGINT while the outputs are being removed (as atomic_output does on any interrupt)
SECOND_DURING_CLEANUP = textwrap.dedent("""
    import os, signal, sys
    from napari_unwind import cli

    def job(args):
        try:
            os.kill(os.getpid(), signal.SIGTERM)  # raises here (os.kill runs the handlers at once)
        except KeyboardInterrupt:
            os.kill(os.getpid(), signal.SIGINT)
            print("cleanup finished", flush=True)
            raise
        return 0

    cli.cmd_info = job
    sys.exit(cli.main(["info", "x"]))
""")


def test_second_signal_during_cleanup_is_ignored():
    """The cleanup runs to its end and the first signal's status stands (143, not 130)."""
    proc = _start(SECOND_DURING_CLEANUP)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 143 and out == "cleanup finished\n", (proc.returncode, out, err)
    assert error_lines(err) == ["unwind: terminated (SIGTERM); no partial output was left behind"], err


# the C-level SIGINT handler before and after one fTetWild call, and what a SIGINT then does; "in-process" calls the
# compiled mesher in this process, as tetrahedralize once did
C_HANDLER = textwrap.dedent("""
    import ctypes, sys

    def c_handler(signum):  # sa_handler, the first field of libc's struct sigaction (glibc, musl, macOS)
        buf = ctypes.create_string_buffer(512)
        assert ctypes.CDLL(None).sigaction(signum, None, buf) == 0
        return int.from_bytes(buf.raw[:ctypes.sizeof(ctypes.c_void_p)], sys.byteorder)
""")
IN_PROCESS = textwrap.dedent("""
    def in_process(v, f, **kw):
        import numpy as np
        o = {"edge_length_fac": 0.05, "epsilon": 1e-3, **kw}
        V, T = _compat.tetwild_extension().tetrahedralize_mesh(
            np.ascontiguousarray(v, float), np.ascontiguousarray(f, np.uint32), True, False, o["edge_length_fac"],
            0.0, o["epsilon"], 10.0, False, 0, 80, 6, True, True, False, np.empty((0, 3)),
            np.empty((0, 4), np.int32), np.empty(0))
        return V, T
""")
AFTER_TETWILD = C_HANDLER + textwrap.dedent("""
    import os, signal
    import numpy as np
    from napari_unwind import _compat
""") + IN_PROCESS + textwrap.dedent("""
    mesh = in_process if sys.argv[1] == "in-process" else _compat.tetrahedralize
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    before = c_handler(signal.SIGINT)
    mesh(v, f)
    after = c_handler(signal.SIGINT)
    print(before, after, signal.getsignal(signal.SIGINT) is signal.default_int_handler, flush=True)
    try:
        os.kill(os.getpid(), signal.SIGINT)
    except KeyboardInterrupt:
        print("KeyboardInterrupt", flush=True)
""")


@pytest.mark.skipif(os.name != "posix", reason="C-level signal handlers: POSIX")
def test_tetrahedralize_leaves_sigint_alone():
    """After tetrahedralize, SIGINT's C-level handler is Python's still and Ctrl-C raises KeyboardInterrupt.

    The compiled mesher called in the process shows why it runs in a child: SIG_DFL (0) behind Python's back
    (getsignal still says Python's handler), and SIGINT kills the process."""
    procs = {mode: _start(AFTER_TETWILD, mode) for mode in ("child", "in-process")}
    res = {mode: p.communicate(timeout=120) + (p.returncode,) for mode, p in procs.items()}
    out, err, code = res["child"]
    lines = out.splitlines()
    before, after, python_view = lines[0].split()
    assert int(before) > 1 and after == before and python_view == "True", (out, err)
    assert lines[1:] == ["KeyboardInterrupt"] and code == 0, (out, err)
    out, err, code = res["in-process"]
    before, after, python_view = out.splitlines()[0].split()
    assert int(before) > 1 and after == "0" and python_view == "True", ("fTetWild no longer resets SIGINT?", out)
    assert code == -signal.SIGINT, (code, out, err)


# a library caller meshing a sphere of ~20k triangles (seconds of fTetWild), its first call in the process; numpy's
# OpenBLAS threads are running (a matrix product first)
DURING_TETWILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from skimage.measure import marching_cubes
    from napari_unwind import _compat
""") + IN_PROCESS + textwrap.dedent("""
    a = np.random.default_rng(0).random((400, 400))
    a @ a  # OpenBLAS starts its threads
    z, y, x = np.mgrid[:72, :72, :72] - 35.5
    v, f, _, _ = marching_cubes(np.sqrt(z * z + y * y + x * x), 32.0)
    mesh = in_process if sys.argv[1] == "in-process" else _compat.tetrahedralize
    print("meshing", flush=True)
    t0 = time.monotonic()
    try:
        mesh(v, f, edge_length_fac=0.02, epsilon=5e-4)
    except KeyboardInterrupt:
        print("KeyboardInterrupt", flush=True)
        sys.exit(7)
    print(f"finished in {time.monotonic() - t0:.1f} s", flush=True)
""")


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[-1][0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children").exists(),
                    reason="needs Linux's /proc/PID/task/PID/children")
@pytest.mark.parametrize("to", ["process", "group"])
def test_sigint_during_first_tetwild_call(tmp_path, to):
    """SIGINT while fTetWild runs for the first time in a library process, sent to the process alone or to its
    process group (a terminal's Ctrl-C): KeyboardInterrupt in the caller, the mesher's process gone, its
    temporary folder removed. The mesher called in the process instead dies with SIGINT (-2) both ways: numpy's
    OpenBLAS threads take the signal and meet geogram's SIG_DFL."""
    for mode in ("child", "in-process"):
        tmp = tmp_path / mode
        tmp.mkdir()
        proc = subprocess.Popen([sys.executable, "-c", DURING_TETWILD, mode], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, preexec_fn=_default_sigint,
                                start_new_session=True, env={**os.environ, "TMPDIR": str(tmp)})
        try:
            assert proc.stdout.readline() == "meshing\n", proc.communicate()
            time.sleep(1.5)  # fTetWild loaded and running (the child's start takes about 0.5 s)
            meshers = _children(proc.pid)
            assert (len(meshers) == 1) == (mode == "child"), (mode, meshers)
            assert proc.poll() is None, (mode, proc.communicate())
            if to == "group":
                os.killpg(proc.pid, signal.SIGINT)
            else:
                proc.send_signal(signal.SIGINT)
            out, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
        if mode == "in-process":
            assert proc.returncode == -signal.SIGINT, (to, proc.returncode, out, err[-1000:])
            continue
        assert proc.returncode == 7 and out == "KeyboardInterrupt\n", (to, proc.returncode, out, err[-2000:])
        assert not any(_alive(pid) for pid in meshers), meshers
        assert list(tmp.iterdir()) == [], list(tmp.iterdir())
