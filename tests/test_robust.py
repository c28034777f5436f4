"""Never crash, never corrupt, never lie: streams, files, signals, settings, numbers, configs and
unforeseen failures through the command line (exit 2 with one line, nothing partial at -o)."""

from __future__ import annotations

import errno
import io
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ncfix
from ncfix.cli import main
from ncfix.errors import InternalError, NcfixError

PROGRAM = b"%\nG21 G90\nG1 X10 Y0 Z5 I0 J0 K1 F1200\nX20 (done)\r\nM30\n%\n"
FLIP = b"G21 G90\nG1 X0 Y0 Z90 I0 J0 K1 F1000\nG1 X5 Y0 Z90 I0 J0 K-1\nG1 X10 Y0 Z90\nM30\n"


def ncfix_process(*args, stdin=b"", cwd=None, shell_suffix=""):
    """The command line in a child process (for what only real file descriptors show)."""
    if shell_suffix:
        cmd = " ".join([f"'{sys.executable}'", "-m", "ncfix", *(f"'{a}'" for a in args)]) + " " + shell_suffix
        return subprocess.run(["bash", "-c", cmd], input=stdin, capture_output=True, cwd=cwd)
    return subprocess.run([sys.executable, "-m", "ncfix", *map(str, args)], input=stdin, capture_output=True, cwd=cwd)


def run_main(argv, capsysbinary):
    """main() in this process: (status, standard output, standard error as text)."""
    status = main([str(a) for a in argv])
    captured = capsysbinary.readouterr()
    return status, captured.out, captured.err.decode()


def revolved_head(folder: Path, segments: int = 16) -> Path:
    """A small closed nozzle: a cone from the tip (origin) to radius 3 mm, a body to 22 mm."""
    mesh = trimesh.creation.revolve(np.array([[0.0, 0.0], [3.0, 2.0], [3.0, 22.0], [0.0, 22.0]]), sections=segments)
    path = folder / "head.stl"
    mesh.export(path)
    return path


@pytest.fixture
def program(tmp_path):
    path = tmp_path / "in.nc"
    path.write_bytes(PROGRAM)
    return path


# -- item 2: a 180° turn of the tool vector ----------------------------------------------------
@pytest.mark.parametrize("check", [True, False])
def test_a_half_turn_of_the_tool_vector_is_checked_not_a_crash(tmp_path, capsysbinary, check):
    src = tmp_path / "flip.nc"
    src.write_bytes(FLIP)
    head = revolved_head(tmp_path)
    status, out, err = run_main([src, "--head", head, "-q"] + (["--check"] if check else []), capsysbinary)
    assert (status, err) == (0, "")
    assert out == FLIP  # --check: the input byte for byte; fix: nothing collides, nothing changes


def test_a_half_turn_turns_in_the_documented_plane():
    from ncfix.collision.path import PathChecker
    from ncfix.profiles import load_profile

    path = PathChecker(None, load_profile("ijk"), 6.0, 0.5)
    ws = np.array([[0.0, 0, 90, 0, 0, 1]])
    we = np.array([[5.0, 0, 90, 0, 0, -1]])
    t = np.linspace(0.0, 1.0, 9)
    words = path._along(None, ws, we, np.zeros(9, dtype=np.int64), t, np.zeros(1, dtype=bool))
    n = words[:, 3:6]
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    assert np.allclose(n[4], [1.0, 0.0, 0.0])  # through +X (half_turn_direction of +Z)
    assert np.allclose(n[0], [0, 0, 1]) and np.allclose(n[-1], [0, 0, -1], atol=1e-12)
    # A vector near ±X turns through +Y instead.
    ws[0, 3:6], we[0, 3:6] = [1, 0, 0], [-1, 0, 0]
    words = path._along(None, ws, we, np.zeros(9, dtype=np.int64), t, np.zeros(1, dtype=bool))
    assert np.allclose(words[4, 3:6], [0.0, 1.0, 0.0])


# -- item 4: streams and files -----------------------------------------------------------------
@pytest.mark.parametrize(
    "redirect, message",
    [
        ("<&-", "ncfix: error: cannot read standard input: it is closed "
                "(give the NC program's path or redirect standard input)"),
        (">&-", "ncfix: error: cannot write standard output: it is closed (give -o OUTPUT or redirect standard output)"),
        (">/dev/full", "ncfix: error: cannot write standard output: No space left on device "
                       "(free some space on that disk or write elsewhere)"),
    ],
)
def test_closed_and_full_standard_streams_exit_2_with_one_line(tmp_path, program, redirect, message):
    if redirect == ">/dev/full" and not Path("/dev/full").exists():
        pytest.skip("no /dev/full here")
    args = ["-"] if redirect == "<&-" else [program]
    done = ncfix_process(*args, "-q", shell_suffix=redirect, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.decode() == message + "\n"


def test_closed_standard_streams_in_process(monkeypatch, program, capsys):
    monkeypatch.setattr(sys, "stdin", None)
    assert main(["-", "-q"]) == 2
    assert "cannot read standard input: it is closed" in capsys.readouterr().err
    monkeypatch.setattr(sys, "stdout", None)
    assert main([str(program), "-q"]) == 2
    assert main(["--list-machines"]) == 2


def test_a_closed_standard_error_never_writes_to_standard_output(monkeypatch, program, capsysbinary):
    monkeypatch.setattr(sys, "stderr", None)
    assert main([str(program)]) == 0
    assert main(["missing.nc"]) == 2
    assert capsysbinary.readouterr().out == PROGRAM


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full here")
@pytest.mark.parametrize("option", ["-o", "--report", "--html"])  # (an empty diff writes no byte)
def test_writing_to_a_full_device_is_an_error_and_the_device_stays(tmp_path, program, option, capsysbinary):
    out = tmp_path / "out.nc"
    argv = [program, "-q", option, "/dev/full"] + (["-o", out] if option != "-o" else [])
    status, _, err = run_main(argv, capsysbinary)
    assert status == 2
    assert err == ("ncfix: error: cannot write '/dev/full': No space left on device "
                   "(free some space on that disk or write elsewhere)\n")
    assert Path("/dev/full").is_char_device()
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["in.nc"]


class FullDisk:
    """A file whose writes fail with ENOSPC after ``room`` bytes (a full file system)."""

    def __init__(self, raw, room):
        self.raw, self.room = raw, room

    def write(self, data):
        if len(data) > self.room:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self.raw.write(data)

    def __getattr__(self, attr):
        return getattr(self.raw, attr)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.raw.close()


@pytest.mark.parametrize("target", ["output", "report"])
def test_a_full_file_system_leaves_neither_output_nor_temporary_file(tmp_path, program, monkeypatch, capsysbinary,
                                                                     target):
    import ncfix.fileio as fileio

    real_fdopen = os.fdopen
    full = tmp_path / ("out.nc" if target == "output" else "r.json")
    monkeypatch.setattr(fileio.os, "fdopen", lambda fd, mode: FullDisk(real_fdopen(fd, mode), 0)
                        if f".{full.name}." in os.readlink(f"/proc/self/fd/{fd}") else real_fdopen(fd, mode))
    status, _, err = run_main([program, "-q", "-o", tmp_path / "out.nc", "--report", tmp_path / "r.json"],
                              capsysbinary)
    assert status == 2
    assert err == f"ncfix: error: cannot write '{full}': No space left on device (free some space on that disk or write elsewhere)\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.nc"]


def test_output_onto_a_fifo_is_written_through(tmp_path, program, capsysbinary):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    got = []
    reader = threading.Thread(target=lambda: got.append(fifo.read_bytes()))
    reader.start()
    status, out, err = run_main([program, "-q", "-o", fifo], capsysbinary)
    reader.join(timeout=30)
    assert (status, out, err) == (0, b"", "")
    assert got == [PROGRAM] and fifo.is_fifo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.nc", "pipe"]


def test_output_onto_a_symlink_replaces_its_target_and_keeps_the_link(tmp_path, program, capsysbinary):
    (tmp_path / "real.nc").write_bytes(b"old\n")
    os.chmod(tmp_path / "real.nc", 0o640)
    (tmp_path / "link.nc").symlink_to("real.nc")
    assert run_main([program, "-q", "-o", tmp_path / "link.nc"], capsysbinary)[0] == 0
    assert (tmp_path / "link.nc").is_symlink() and os.readlink(tmp_path / "link.nc") == "real.nc"
    assert (tmp_path / "real.nc").read_bytes() == PROGRAM
    assert (tmp_path / "real.nc").stat().st_mode & 0o777 == 0o640


def test_short_writes_are_completed_and_a_failure_after_one_is_reported():
    from ncfix.fileio import Output

    class Dribble(io.RawIOBase):
        def __init__(self, fail_after=None):
            self.data, self.fail_after = bytearray(), fail_after

        def writable(self):
            return True

        def write(self, b):
            if self.fail_after is not None and len(self.data) >= self.fail_after:
                raise OSError(errno.EIO, "Input/output error")
            self.data += bytes(b[:3])
            return min(3, len(b))

    raw = Dribble()
    assert Output(raw, "x").write(b"0123456789") == 10 and bytes(raw.data) == b"0123456789"
    with pytest.raises(NcfixError, match="cannot write 'x': Input/output error"):
        Output(Dribble(fail_after=6), "x").write(b"0123456789")


def test_a_reader_that_stops_early_on_one_long_line_gives_141(tmp_path):
    long = tmp_path / "long.nc"
    long.write_bytes(b"G1 X1 Y2 Z3 (" + b"c" * 10_000_000 + b")\n")
    done = ncfix_process(long, shell_suffix="| head -c 10; exit ${PIPESTATUS[0]}")
    assert done.stdout == b"G1 X1 Y2 Z"
    assert done.returncode == 141
    assert done.stderr == b""


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_signal_leaves_no_temporary_file(tmp_path, signum):
    child = subprocess.Popen([sys.executable, "-m", "ncfix", "-", "-o", str(tmp_path / "out.nc"), "-q"],
                             stdin=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path)
    child.stdin.write(PROGRAM[:20])  # the rest never comes: ncfix waits with its temporary file open
    child.stdin.flush()
    deadline = time.monotonic() + 60
    while not list(tmp_path.glob(".out.nc.*.tmp")) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert list(tmp_path.glob(".out.nc.*.tmp"))
    child.send_signal(signum)
    assert child.wait(timeout=60) == 128 + signum
    child.stdin.close()
    assert child.stderr.read() == b""
    assert list(tmp_path.iterdir()) == []
