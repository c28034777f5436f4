"""ncfix.process (the CAM-hook API), the command line running the same code, --diff, progress, the README hook."""

from __future__ import annotations

import io
import json
import os
import re
import runpy
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ncfix
from ncfix.cli import main
from ncfix.errors import ConfigError, NcfixError, ProgramError

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"
PROGRAM = b"%\nG21 G90\nG1 X10 Y0 Z5 I0 J0 K1 F1200\nX20 (done)\r\nG1 X30 Y1 Z5\nG1 X40 Y2 Z5\nM30\n%"


@pytest.fixture
def program(tmp_path):
    path = tmp_path / "in.nc"
    path.write_bytes(PROGRAM)
    return path


class FakeCorrector:
    """Stands in for the correction stage: tilts the blocks on ``tilt`` lines, leaves ``stuck`` lines unresolved."""

    def __init__(self, options, report, tilt=(), stuck=()):
        self.options, self.report, self.tilt, self.stuck = options, report, set(tilt), set(stuck)

    def push(self, chunk):
        s = self.report.summary
        for i in np.flatnonzero(chunk.motion >= 0).tolist():
            line = chunk.first_lineno + i
            if line in self.tilt | self.stuck:
                s["colliding_blocks_before"] += 1
                self.report.collisions.append({"line": line, "bodies": ["part:mold.stl"], "penetration_mm": 0.5,
                                               "clearance_mm": -0.5})
            if line in self.stuck and not self.options.check:
                s["unresolved_blocks"] += 1
                self.report.unresolved.append({"line": line, "bodies": ["part:mold.stl"], "penetration_mm": 0.5,
                                               "reason": "no free orientation within --max-tilt 30°"})
            if line in self.tilt and not self.options.check:
                words = chunk.words[i].copy()
                words[3:6] = [0.1, 0.0, 0.994987]
                chunk.new_words[i] = words
                chunk.reasons[i] = "collision"
                s["changed_blocks"] += 1
                s["max_tilt_deg"] = max(s["max_tilt_deg"], 5.74)
                self.report.changes.append({"line": line, "before": None, "after": None, "reason": "collision",
                                            "tilt_deg": 5.74, "step_deg": 5.74, "bodies": ["part:mold.stl"],
                                            "clearance_before_mm": -0.5, "clearance_after_mm": 0.2,
                                            "point": [float(v) for v in words[:3]]})
        return [chunk]

    def flush(self):
        return []


@pytest.fixture
def corrector(monkeypatch):
    """``corrector(tilt=..., stuck=...)`` replaces the pipeline's stages with a FakeCorrector."""

    def install(tilt=(), stuck=()):
        monkeypatch.setattr("ncfix.pipeline.build_stages",
                            lambda options, profile, report, box=None: [FakeCorrector(options, report, tilt, stuck)])

    return install


# -- ncfix.process ---------------------------------------------------------------------------------


def test_process_paths_passes_the_program_through_and_returns_the_report(program, tmp_path):
    out = tmp_path / "out.nc"
    report = ncfix.process(program, out)
    assert out.read_bytes() == PROGRAM
    assert report.exit_code == 0 and report.summary["lines"] == 8 and report.summary["motion_blocks"] == 4
    assert report.input == str(program)
    assert report.verdict == "no --head given: the program was read and passed through unchanged: exit 0"


def test_written_files_get_the_modes_a_plain_open_would_give(program, tmp_path):
    umask = os.umask(0o022)
    try:
        out, report = tmp_path / "out.nc", tmp_path / "r.json"
        ncfix.process(program, out, report=str(report))
        assert (out.stat().st_mode & 0o777) == 0o644 and (report.stat().st_mode & 0o777) == 0o644
        out.chmod(0o600)  # an existing file keeps its own mode
        ncfix.process(program, out)
        assert out.stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(umask)


def test_process_streams(program):
    out = io.BytesIO()
    report = ncfix.process(io.BytesIO(PROGRAM), out, machine="ijk")
    assert out.getvalue() == PROGRAM and report.input == "<stream>"


def test_text_streams_are_refused_with_a_hint():
    with pytest.raises(ConfigError, match=r"src is a text stream \(open the file in binary mode"):
        ncfix.process(io.StringIO("G1 X1\n"), io.BytesIO())
    with pytest.raises(ConfigError, match=r"dst is a text stream"):
        ncfix.process(io.BytesIO(b"G1 X1\n"), io.StringIO())


@pytest.mark.parametrize(
    "options, message",
    [
        ({"standof": 4}, "ncfix.process() got an unknown option 'standof' (did you mean 'standoff'?)"),
        ({"colour": "red"}, "ncfix.process() got an unknown option 'colour' (known options: machine, head, "),
        ({"standoff": "-1"}, "--standoff has a bad value '-1' (give a number from 0 up to 1000)"),  # as the CLI says
        ({"max_step": "abc"}, "--max-step has a bad value 'abc' (give a number)"),
        ({"deposit_codes": "M3"}, "--deposit-codes has a bad value 'M3' (give two different codes ON,OFF, e.g. M3,M5)"),
        ({"machine": "table-acc"}, "unknown machine 'table-acc' (did you mean 'table-ac'? known machines: "),
    ],
)
def test_bad_options_raise_the_command_lines_messages(options, message, program, tmp_path):
    out = tmp_path / "out.nc"
    with pytest.raises(NcfixError) as caught:
        ncfix.process(program, out, **options)
    assert str(caught.value).startswith(message), str(caught.value)
    assert not out.exists()


def test_config_is_read_only_when_given_and_keywords_win(program, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ncfix.toml").write_text('[ncfix]\nmachine = "table-ac"\nstandoff = 4.5\n')
    assert ncfix.process(program, tmp_path / "o.nc").machine == "ijk"  # ./ncfix.toml is not read
    rotary = tmp_path / "rotary.nc"  # A/C words: what table-ac reads
    rotary.write_bytes(PROGRAM.replace(b"I0 J0 K1", b"A0 C0"))
    report = ncfix.process(rotary, tmp_path / "o.nc", config=tmp_path / "ncfix.toml")
    assert report.machine == "table-ac" and report.options.standoff == 4.5
    report = ncfix.process(program, tmp_path / "o.nc", config="ncfix.toml", machine="ijk", part=[Path("m.stl")])
    assert report.machine == "ijk" and report.options.standoff == 4.5 and report.options.part == ("m.stl",)
    (tmp_path / "bad.toml").write_text("[ncfix]\nstand_off = 4\n")
    with pytest.raises(ConfigError, match=re.escape("bad.toml: unknown key 'stand_off' in [ncfix] (did you mean")):
        ncfix.process(program, tmp_path / "o.nc", config="bad.toml")


def test_an_error_in_the_program_raises_and_writes_nothing(tmp_path):
    src = tmp_path / "bad.nc"
    src.write_bytes(b"G21\nG1 X1 Y1 Z1\nG1 X1.2.3\n")
    names = {"out.nc", "r.json", "d.diff", "r.html"}
    with pytest.raises(ProgramError, match=r"bad.nc:3: the X word 'X1.2.3' is not a number"):
        ncfix.process(src, tmp_path / "out.nc", report=tmp_path / "r.json", diff=tmp_path / "d.diff",
                      html=tmp_path / "r.html")
    assert {p.name for p in tmp_path.iterdir()} == {"bad.nc"}
    assert not names & {p.name for p in tmp_path.iterdir()}


def test_a_missing_output_folder_is_refused_before_anything_is_written(program, tmp_path):
    with pytest.raises(NcfixError, match=r"cannot write '.*nowhere/r.html': folder '.*nowhere' does not exist"):
        ncfix.process(program, tmp_path / "out.nc", html=tmp_path / "nowhere" / "r.html")
    assert not (tmp_path / "out.nc").exists()
    with pytest.raises(NcfixError, match=r"cannot read '.*missing.nc': no such file \(check the path\)"):
        ncfix.process(tmp_path / "missing.nc", tmp_path / "out.nc")


def test_progress_is_called_per_chunk_with_bytes_and_lines(tmp_path):
    src = tmp_path / "long.nc"
    src.write_bytes(b"".join(b"G1 X%d Y1 Z1 I0 J0 K1\n" % i for i in range(10_000)))
    calls = []
    ncfix.process(src, io.BytesIO(), progress=lambda done, lines: calls.append((done, lines)))
    assert [lines for _, lines in calls] == [4096, 8192, 10_000]
    assert calls[-1][0] == src.stat().st_size and calls[0][0] < calls[1][0]


def test_process_writes_report_diff_and_html_of_a_fixed_program(program, tmp_path, corrector):
    corrector(tilt=[5], stuck=[6])
    out, rep, diff, page = (tmp_path / n for n in ("out.nc", "r.json", "d.diff", "r.html"))
    report = ncfix.process(program, out, report=rep, diff=diff, html=page)
    assert report.exit_code == 1 and out.exists()
    data = json.loads(rep.read_text())
    assert data["changes"][0]["before"] == "G1 X30 Y1 Z5" and data["changes"][0]["after"] == "G1 X30 Y1 Z5 I0.100000 J0.000000 K0.994987"
    assert data["unresolved"] == [{"line": 6, "bodies": ["part:mold.stl"], "penetration_mm": 0.5,
                                   "reason": "no free orientation within --max-tilt 30°"}]
    # line 6 says no vector: it would inherit line 5's tilt, so it restates the programmed one
    assert diff.read_text() == (f"--- {program}\n+++ {out}\n@@ -5,1 +5,1 @@\n-G1 X30 Y1 Z5\n"
                                "+G1 X30 Y1 Z5 I0.100000 J0.000000 K0.994987\n"
                                "@@ -6,1 +6,1 @@\n-G1 X40 Y2 Z5\n+G1 X40 Y2 Z5 I0.000000 J0.000000 K1.000000\n")
    assert data["changes"][1]["line"] == 6 and data["changes"][1]["reason"] == "blend"
    html = page.read_text()
    assert 'href="#L5"' in html and 'id="L5"' in html and "no free orientation within --max-tilt 30°" in html


# -- the command line runs the same code -----------------------------------------------------------


def test_cli_diff_applies_with_patch_to_reproduce_the_output(program, tmp_path, corrector, capsys):
    if shutil.which("patch") is None:
        pytest.skip("patch is not installed")
    corrector(tilt=[3, 5])
    out, diff = tmp_path / "out.nc", tmp_path / "d.diff"
    assert main([str(program), "-o", str(out), "--diff", str(diff), "--head", "h.stl"]) == 0
    assert out.read_bytes() != PROGRAM
    copy = tmp_path / "copy.nc"
    copy.write_bytes(PROGRAM)
    done = subprocess.run(["patch", "-s", str(copy), str(diff)], capture_output=True)
    assert done.returncode == 0, done.stdout + done.stderr
    assert copy.read_bytes() == out.read_bytes()
    err = capsys.readouterr().err
    assert "4 blocks changed: 2 tilted off a collision, 2 blended into ramps" in err  # 4 and 6 restate the vector
    assert err.rstrip().endswith("all 2 colliding blocks fixed: 2 blocks tilted, 2 ramp blocks blended; "
                                 "the output has no detected collision: exit 0")


def test_cli_check_writes_an_empty_diff_and_exits_1_on_collisions(program, tmp_path, corrector, capsysbinary):
    corrector(tilt=[5])
    diff = tmp_path / "d.diff"
    diff.write_text("old")
    assert main([str(program), "--check", "--diff", str(diff), "--head", "h.stl", "-q"]) == 1
    captured = capsysbinary.readouterr()
    assert captured.out == PROGRAM and captured.err == b""
    assert diff.read_bytes() == b""


def test_cli_unresolved_blocks_exit_1_with_output_written_and_listed(program, tmp_path, corrector, capsys):
    corrector(stuck=[6])
    out = tmp_path / "out.nc"
    assert main([str(program), "-o", str(out), "--head", "h.stl"]) == 1
    assert out.read_bytes() == PROGRAM
    err = capsys.readouterr().err
    assert re.search(r"\b6\s+part:mold.stl\s+–\s+0.500\s+no free orientation within --max-tilt 30°", err)
    assert err.rstrip().endswith("1 colliding block could not be fixed and is left as programmed (0 of 1 fixed): exit 1")


def test_cli_and_api_give_the_same_output_and_report(program, tmp_path, corrector):
    corrector(tilt=[3], stuck=[6])
    assert main([str(program), "-o", str(tmp_path / "a.nc"), "--report", str(tmp_path / "a.json"),
                 "--head", "h.stl", "--standoff", "4", "-q"]) == 1
    report = ncfix.process(program, tmp_path / "b.nc", report=tmp_path / "b.json", head="h.stl", standoff="4")
    assert (tmp_path / "a.nc").read_bytes() == (tmp_path / "b.nc").read_bytes()
    a, b = (json.loads((tmp_path / n).read_text()) for n in ("a.json", "b.json"))
    for data in (a, b):
        data["summary"]["seconds"] = 0
        del data["settings"]["report"], data["settings"]["quiet"]
    assert a == b and report.exit_code == 1


def run_in_terminal(args: list[str], cwd: Path) -> bytes:
    """Run ncfix with standard error on a pseudo-terminal; returns what it wrote there."""
    import pty

    master, slave = pty.openpty()
    done = subprocess.Popen([sys.executable, "-m", "ncfix", *args], stdout=subprocess.DEVNULL, stderr=slave, cwd=cwd)
    os.close(slave)
    chunks = []
    while True:
        try:
            data = os.read(master, 65536)
        except OSError:
            break
        if not data:
            break
        chunks.append(data)
    done.wait(timeout=60)
    os.close(master)
    return b"".join(chunks)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="pseudo-terminals as on Linux")
def test_progress_bar_only_on_a_terminal_and_never_with_q(tmp_path):
    big = tmp_path / "big.nc"
    big.write_bytes(b"G1 X1 Y2 Z3 I0 J0 K1\n" * 50_000)
    shown = run_in_terminal([str(big), "-o", str(tmp_path / "o.nc")], tmp_path)
    assert "━".encode() in shown  # the bar
    assert b"50,000 lines" in shown
    assert run_in_terminal([str(big), "-o", str(tmp_path / "o.nc"), "-q"], tmp_path) == b""
    piped = subprocess.run([sys.executable, "-m", "ncfix", str(big), "-o", str(tmp_path / "o.nc")],
                           capture_output=True, cwd=tmp_path)
    assert "━".encode() not in piped.stderr and b"\x1b[" not in piped.stderr


# -- the README's hook example ----------------------------------------------------------------------


def readme_hook() -> str:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text.split("## Using ncfix from a CAM export hook", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, re.S)
    hook = [b for b in blocks if "sys.argv" in b]
    assert len(hook) == 1, "the README's hook section must hold one runnable script"
    return hook[0]


def run_hook(tmp_path: Path, monkeypatch, posted: Path, settings: Path):
    script = tmp_path / "post_export.py"
    script.write_text(readme_hook(), encoding="utf-8")
    monkeypatch.setattr(sys, "argv", [str(script), str(posted), str(tmp_path / "handover.nc"), str(settings)])
    try:
        runpy.run_path(str(script), run_name="__main__")
    except SystemExit as exc:
        return exc.code
    return 0


def test_readme_hook_refuses_a_program_with_unresolved_collisions(tmp_path, monkeypatch, corrector, capsys):
    corrector(tilt=[3], stuck=[5, 6])
    posted = tmp_path / "part.nc"
    posted.write_bytes(PROGRAM)
    code = run_hook(tmp_path, monkeypatch, posted, SAMPLES / "ncfix.toml")
    assert code == (f"post_export: 2 colliding blocks could not be fixed and are left as programmed (1 of 3 fixed): "
                    f"exit 1; NOT handed over (see {tmp_path / 'part'}_ncfix.html)")
    assert not (tmp_path / "handover.nc").exists() and not (tmp_path / "handover.nc.ncfix-tmp").exists()
    err = capsys.readouterr().err
    assert f"post_export: {posted}:5: no free orientation within --max-tilt 30°" in err
    assert json.loads((tmp_path / "part_ncfix.json").read_text())["summary"]["unresolved_blocks"] == 2
    assert (tmp_path / "part_ncfix.html").exists()


def test_readme_hook_hands_over_a_fixed_program(tmp_path, monkeypatch, corrector, capsys):
    corrector(tilt=[3, 5])
    posted = tmp_path / "part.nc"
    posted.write_bytes(PROGRAM)
    assert run_hook(tmp_path, monkeypatch, posted, SAMPLES / "ncfix.toml") == 0
    handed = (tmp_path / "handover.nc").read_bytes()
    assert handed.count(b"K0.994987") == 2 and handed.count(b"\n") == PROGRAM.count(b"\n")
    assert capsys.readouterr().out.strip() == (
        "post_export: all 2 colliding blocks fixed: 2 blocks tilted, 2 ramp blocks blended; the output has no "
        f"detected collision: exit 0; handed over as {tmp_path / 'handover.nc'}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["handover.nc", "part.nc", "part_ncfix.html",
                                                           "part_ncfix.json", "post_export.py"]


def test_readme_hook_reports_a_bad_settings_file(tmp_path, monkeypatch):
    settings = tmp_path / "settings.toml"
    settings.write_text("[ncfix]\nstandoff = -2\n")
    posted = tmp_path / "part.nc"
    posted.write_bytes(PROGRAM)
    code = run_hook(tmp_path, monkeypatch, posted, settings)
    assert code == (f"post_export: {settings}: key 'standoff' has a bad value -2 "
                    "(give a number from 0 up to 1000)")
    assert not (tmp_path / "handover.nc").exists()


@pytest.mark.heavy
def test_readme_hook_on_the_bathtub_sample_matches_the_report(tmp_path):
    """The real thing: head, mold and deposit of samples/ncfix.toml; the hook's status follows the report."""
    posted = tmp_path / "bathtub_273.nc"
    shutil.copy(SAMPLES / "bathtub_273.nc", posted)
    script = tmp_path / "post_export.py"
    script.write_text(readme_hook(), encoding="utf-8")
    handover = tmp_path / "handover.nc"
    done = subprocess.run([sys.executable, str(script), str(posted), str(handover), str(SAMPLES / "ncfix.toml")],
                          capture_output=True, cwd=tmp_path)
    data = json.loads((tmp_path / "bathtub_273_ncfix.json").read_text())
    assert data["summary"]["colliding_blocks_before"] > 0
    if data["unresolved"]:
        assert done.returncode == 1 and not handover.exists(), done.stderr
        assert b"NOT handed over" in done.stderr
    else:
        assert done.returncode == 0 and handover.exists(), done.stderr
        assert handover.read_bytes().count(b"\n") == posted.read_bytes().count(b"\n")
