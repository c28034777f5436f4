"""The command line as docs/contract.md describes it: I/O, config, exit codes and error messages."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from ncfix import __version__
from ncfix.cli import main

PROGRAM = b"%\nG21 G90\nG1 X10 Y0 Z5 I0 J0 K1 F1200\nX20 (done)\r\nM30\n%\n"
ROTARY_PROGRAM = b"%\nG21 G90\nG1 X10 Y0 Z5 A10 C0 F1200\nX20 (done)\r\nM30\n%\n"


def ncfix(*args, stdin=b"", cwd=None):
    return subprocess.run([sys.executable, "-m", "ncfix", *args], input=stdin, capture_output=True, cwd=cwd)


@pytest.fixture
def program(tmp_path):
    path = tmp_path / "in.nc"
    path.write_bytes(PROGRAM)
    return path


def test_stdin_to_stdout_is_exact():
    done = ncfix("-q", stdin=PROGRAM)
    assert (done.returncode, done.stdout, done.stderr) == (0, PROGRAM, b"")


def test_file_to_output_file(program, tmp_path):
    out = tmp_path / "out.nc"
    done = ncfix(str(program), "-o", str(out), "-q")
    assert done.returncode == 0 and done.stdout == b""
    assert out.read_bytes() == PROGRAM


def test_summary_goes_to_stderr_and_program_to_stdout(program):
    done = ncfix(str(program))
    assert done.stdout == PROGRAM
    assert b"motion blocks" in done.stderr


def test_version_and_machine_list():
    assert ncfix("--version").stdout.decode().strip() == f"ncfix {__version__}"
    listing = ncfix("--list-machines").stdout.decode()
    for name in ("ijk", "sinumerik-vector", "heidenhain-ln", "table-ac", "table-bc", "multiaxis-3dp-bc"):
        assert f"\n{name} " in "\n" + listing


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing.nc"], "ncfix: error: cannot read 'missing.nc': no such file (check the path)"),
        (["."], "ncfix: error: cannot read '.': it is a folder (give the NC program's file path)"),
        (["--machine", "table-acc", "-"], "ncfix: error: unknown machine 'table-acc' (did you mean 'table-ac'? known machines: "),
        (["--standoff", "-1", "-"], "ncfix: error: --standoff has a bad value '-1' (give a number from 0 up to 1000)"),
        (["--max-step", "abc", "-"], "ncfix: error: --max-step has a bad value 'abc' (give a number)"),
        (["--head-tip", "1,2", "-"], "ncfix: error: --head-tip has a bad value '1,2' (give three numbers X,Y,Z, e.g. 0,0,1)"),
        (["--deposit-codes", "M3", "-"], "ncfix: error: --deposit-codes has a bad value 'M3' (give two different codes ON,OFF, e.g. M3,M5)"),
        (["-c", "nope.toml", "-"], "ncfix: error: config file 'nope.toml' does not exist (give an existing file with -c/--config)"),
    ],
)
def test_usage_errors_exit_2_with_a_message(args, message, tmp_path):
    done = ncfix(*args, stdin=PROGRAM, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.decode().startswith(message), done.stderr.decode()
    assert b"Traceback" not in done.stderr


def test_bad_axis_word_exits_2_naming_the_line_and_writes_no_output(tmp_path):
    src = tmp_path / "bad.nc"
    src.write_bytes(b"G21\nG1 X1 Y1 Z1\nG1 X1.2.3\n")
    out = tmp_path / "out.nc"
    done = ncfix(str(src), "-o", str(out))
    assert done.returncode == 2
    assert done.stderr.decode().strip() == (
        f"ncfix: error: {src}:3: the X word 'X1.2.3' is not a number "
        "(correct the value in the program; ncfix never guesses a position)")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [src]  # no temporary file left behind


def test_config_file_is_read_and_command_line_wins(tmp_path, program):
    (tmp_path / "ncfix.toml").write_text('[ncfix]\nmachine = "table-ac"\nstandoff = 4.5\n')
    report = tmp_path / "r.json"
    rotary = tmp_path / "rotary.nc"
    rotary.write_bytes(ROTARY_PROGRAM)
    done = ncfix(str(rotary), "--report", str(report), "-q", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    data = json.loads(report.read_text())
    assert data["machine"] == "table-ac" and data["settings"]["standoff"] == 4.5
    done = ncfix(str(program), "--report", str(report), "--machine", "ijk", "-q", cwd=tmp_path)
    assert json.loads(report.read_text())["machine"] == "ijk"


def test_unknown_config_key_suggests_the_closest(tmp_path):
    (tmp_path / "ncfix.toml").write_text("[ncfix]\nstand_off = 4\n")
    done = ncfix("-", stdin=PROGRAM, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.decode().strip() == (
        "ncfix: error: ncfix.toml: unknown key 'stand_off' in [ncfix] (did you mean 'standoff'?)")


def test_bad_config_value_names_the_key(tmp_path):
    (tmp_path / "ncfix.toml").write_text('[ncfix]\npitch = "fine"\n')
    done = ncfix("-", stdin=PROGRAM, cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr.decode().strip() == (
        "ncfix: error: ncfix.toml: key 'pitch' has a bad value 'fine' (give a number)")


def test_report_schema_and_empty_diff_on_pass_through(tmp_path, program):
    report, diff = tmp_path / "r.json", tmp_path / "d.diff"
    done = ncfix(str(program), "--check", "--report", str(report), "--diff", str(diff), "-q")
    assert done.returncode == 0 and done.stdout == PROGRAM
    data = json.loads(report.read_text())
    assert data["schema"] == 1 and data["ncfix"] == __version__ and data["input"] == str(program)
    assert data["summary"]["lines"] == 6 and data["summary"]["motion_blocks"] == 2
    assert data["changes"] == [] and data["unresolved"] == []
    assert diff.read_text() == ""


def test_broken_pipe_ends_quietly(tmp_path):
    big = tmp_path / "big.nc"
    big.write_bytes(b"G1 X1 Y2 Z3 I0 J0 K1\n" * 200_000)
    cmd = f"{sys.executable} -m ncfix {big} | head -n 2"
    done = subprocess.run(["bash", "-c", cmd], capture_output=True)
    assert done.stdout == b"G1 X1 Y2 Z3 I0 J0 K1\n" * 2
    assert done.stderr == b""


def test_main_can_be_called_in_process(program, capsysbinary):
    assert main([str(program), "-q"]) == 0
    assert capsysbinary.readouterr().out == PROGRAM


def test_config_beside_the_input_is_used_when_none_is_in_the_working_folder(tmp_path):
    folder = tmp_path / "programs"
    folder.mkdir()
    (folder / "ncfix.toml").write_text('[ncfix]\nmachine = "table-ac"\n')
    (folder / "p.nc").write_bytes(ROTARY_PROGRAM)
    report = tmp_path / "r.json"
    work = tmp_path / "work"
    work.mkdir()
    done = ncfix(str(folder / "p.nc"), "--report", str(report), "-q", cwd=work)
    assert done.returncode == 0, done.stderr
    assert json.loads(report.read_text())["machine"] == "table-ac"
