"""Property-based: whatever the program, the options or the meshes, ncfix never crashes or lies.

Programs are built from the words of every built-in profile (motion, tool vectors, arcs, modal
codes, E words, comments) mixed with junk bytes, bytes that are not UTF-8, odd blanks and line
ends, long lines and values no controller accepts (``nan``, ``1e999``, ``1.2.3``). For each:

- the exit status is 0, 1 or 2, never a traceback, never an internal error, no RuntimeWarning;
- exit 2 says so on one line (with -q);
- ``--check`` writes the input byte for byte (exit 0/1), or a prefix of it (exit 2: what was
  streamed before the error);
- without ``--head`` the output is the input; with it, the output has the input's lines.

The command line runs in this process (``ncfix.cli.main`` with standard streams swapped). Each
property runs twice: all its examples in CI's heavy step (1,060 in all, a few minutes) and the first
tenth of them in the README's fast run. Most run without a head; a fraction with a small head and
plate, and a set of broken meshes.

Every run on every machine tries the same examples in the same order, so a failure in CI is a
failure here:

- the seed is the test's own source (``derandomize``, no example database), and hypothesis is
  pinned in the ``test`` extra (another release draws other examples from the same seed);
- hypothesis's "local constants" are switched off (``same_examples_everywhere``): it mixes into
  its draws the numbers and strings written in the source of every imported module outside
  site-packages, so the examples changed with how ncfix is installed (editable here, not in CI),
  with which modules earlier test files had imported, and with any literal edited in ncfix;
- the strategies draw from lists and ranges written here (no set or dict order) and compute with
  ``math`` (numpy's vectorised sine and cosine depend on the CPU); the default text alphabet is
  every code point but surrogates, whatever the Python's Unicode version;
- the module runs with a cache folder of its own, empty when it starts, and a working folder of
  its own, whatever ran before.

To hunt with other examples, run a copy with ``@seed(k)`` or ``derandomize=False`` and
``--hypothesis-seed=k``; never commit it.
"""

from __future__ import annotations

import io
import math
import os
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, Phase, event, given, settings
from hypothesis import strategies as st
from hypothesis.internal.conjecture import providers

from ncfix.cli import main
from ncfix.profiles import builtin_names, load_profile

PROFILES = {name: load_profile(name) for name in builtin_names()}
# No shrinking: on a shared CI machine a failure is reported as found (still reproducible: derandomized).
COMMON = dict(derandomize=True, deadline=None, database=None, print_blob=True,
              phases=[Phase.explicit, Phase.reuse, Phase.generate],
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                     HealthCheck.filter_too_much, HealthCheck.large_base_example])


def both_runs(examples: int, **strategies):
    """A property as two tests: ``examples`` examples, marked heavy (CI's second step), and a tenth
    of them for the fast run. Returns (heavy test, fast test)."""
    def make(body):
        full = pytest.mark.heavy(settings(max_examples=examples, **COMMON)(given(**strategies)(body)))
        return full, settings(max_examples=max(1, examples // 10), **COMMON)(given(**strategies)(body))
    return make


# -- running the command line in this process ---------------------------------------------------
def run_cli(argv: list[str], stdin: bytes = b"") -> tuple[int, bytes, str, list[warnings.WarningMessage]]:
    """(exit status, standard output, standard error, RuntimeWarnings) of ``ncfix argv``."""
    out = io.BytesIO()
    err = io.StringIO()
    saved = sys.stdin, sys.stdout, sys.stderr
    fake_in, fake_out = io.TextIOWrapper(io.BytesIO(stdin)), io.TextIOWrapper(out, write_through=True)
    sys.stdin, sys.stdout, sys.stderr = fake_in, fake_out, err
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", RuntimeWarning)
            try:
                status = main(argv)
            except SystemExit as exc:  # argparse: a bad choice or a missing value
                status = exc.code if isinstance(exc.code, int) else 2
    finally:
        fake_out.flush()
        sys.stdin, sys.stdout, sys.stderr = saved
    written = out.getvalue()  # before the wrappers go: closing them closes the buffers
    fake_in.detach(), fake_out.detach()
    runtime = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    return status, written, err.getvalue(), runtime


def assert_honest(status: int, out: bytes, err: str, runtime, program: bytes, *, check: bool, quiet: bool,
                  passthrough: bool, argv) -> None:
    event(f"exit {status}")  # pytest --hypothesis-show-statistics shows the mix
    assert status in (0, 1, 2), (status, err, argv)
    assert "Traceback" not in err, (err, argv)
    assert "internal error" not in err, (err, argv)
    assert not runtime, ([str(w.message) for w in runtime], argv)
    if status == 2 and quiet:
        lines = err.splitlines()
        assert len(lines) == 1 or lines[0].startswith("usage:"), (err, argv)
    if check or passthrough:
        if status in (0, 1):
            assert out == program, argv
        else:
            assert program.startswith(out), argv
    elif status in (0, 1):
        assert out.count(b"\n") == program.count(b"\n"), argv


# -- programs ------------------------------------------------------------------------------------
SPECIAL_VALUES = ["nan", "inf", "-inf", "1e999", "1e-05", "1.2.3", "", "#100", "[1+2]", "-", "+", ".", "Q5",
                  "1 2", "0. 5", "99999999999999999999", "-0.", "+.5"]


@st.composite
def number_text(draw, lo=-300.0, hi=300.0, special=0.05):
    if draw(st.floats(0, 1)) < special:
        return draw(st.sampled_from(SPECIAL_VALUES))
    value = draw(st.one_of(st.integers(int(lo), int(hi)).map(float), st.floats(lo, hi, allow_nan=False)))
    style = draw(st.sampled_from(["{:.3f}", "{:g}", "{:.0f}.", "{:.6f}", "{:.1f}", "{:+.3f}", "{:.4f}"]))
    return style.format(value)


def word(profile, letter: str, value: str) -> str:
    if any(ch.isdigit() for ch in letter):  # Siemens A3=
        return f"{letter}={value}"
    if profile.dialect == "heidenhain" and value and value[0] not in "+-":
        value = "+" + value
    return f"{letter}{value}"


@st.composite
def unit_vector_text(draw, profile, special=0.05):
    kinds = ["up", "tilted", "tilted", "down", "partial", "random"] + (["zero"] if special else [])
    kind = draw(st.sampled_from(kinds))
    if kind == "up":
        v = (0.0, 0.0, 1.0)
    elif kind == "down":
        v = (0.0, 0.0, -1.0)
    elif kind == "zero":
        v = (0.0, 0.0, 0.0)
    else:
        tilt = draw(st.floats(0, 40 if kind == "tilted" else 180))
        azimuth = draw(st.floats(-180, 180))
        t, a = math.radians(tilt), math.radians(azimuth)
        v = (math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t))
    letters = profile.kinematics.orientation_letters
    words = [word(profile, letter, f"{c:.6f}") for letter, c in zip(letters, v)]
    if kind == "partial":
        words = draw(st.lists(st.sampled_from(words), max_size=2, unique=True))
    return words


@st.composite
def motion_line(draw, profile, box=((-300, 300),) * 3, special=0.05):
    words = []
    if draw(st.booleans()):
        words.append(f"N{draw(st.integers(0, 99999))}")
    heidenhain = profile.dialect == "heidenhain"
    g = draw(st.sampled_from(["G0", "G1", "G1", "G1", "G2", "G3", ""]))
    if heidenhain:
        words.append(draw(st.sampled_from(["LN", "L", "LN"])))
    elif g:
        words.append(g)
    for axis, (lo, hi) in zip("XYZ", box):
        if draw(st.floats(0, 1)) < 0.8:
            words.append(word(profile, axis, draw(number_text(lo, hi, special))))
    if profile.is_vector:
        if draw(st.floats(0, 1)) < 0.7:
            words += draw(unit_vector_text(profile, special))
    else:
        for letter in profile.kinematics.orientation_letters:
            if draw(st.floats(0, 1)) < 0.6:
                words.append(word(profile, letter, draw(number_text(-120, 400, special))))
    if g in ("G2", "G3") and not heidenhain and draw(st.booleans()):
        words += [f"I{draw(number_text(-20, 20, special))}", f"J{draw(number_text(-20, 20, special))}"]
    if draw(st.floats(0, 1)) < 0.3:
        words.append(f"F{draw(st.integers(1, 6000))}")
    if draw(st.floats(0, 1)) < 0.3:
        words.append(f"E{draw(number_text(-5, 50, special))}")
    sep = draw(st.sampled_from([" ", " ", " ", "", "\t", "  ", " \t"]))
    return sep.join(words)


MODAL = ["G20", "G21", "G90", "G91", "G17", "G18", "G19", "G43.5 H1", "G43.4 H1", "G49", "M3", "M5", "M82", "M83",
         "G92 E0", "M30", "%", "O1234", "TRAORI", "TRAFOOF", "M128", "M129", "M428", "M429",
         "FUNCTION TCPM F TCP AXIS POS", "G28 X0 Y0", "G53 Z0", "G10 L2 P1 X0", "G4 P1", "G80", "G81 Z-1 R1",
         "BEGIN PGM X MM", "END PGM X MM", "CYCLE800(1,\"TC1\",0)", "T1 M6", "S1000 M3", "/G1 X1", "G92 X0 Y0 Z0",
         "M104 S200", "G28"]


@st.composite
def junk_line(draw):
    kind = draw(st.sampled_from(["bytes", "latin", "comment", "long", "blank", "control"]))
    if kind == "bytes":
        return draw(st.binary(max_size=40)).replace(b"\n", b" ")
    if kind == "latin":
        return bytes(draw(st.lists(st.integers(0x80, 0xFF), max_size=20)))
    if kind == "comment":
        text = draw(st.text(max_size=30)).encode("utf-8", "replace").replace(b"\n", b" ")
        return draw(st.sampled_from([b"(%s)", b"; %s", b"(%s", b"G1 X1 (%s) Y2", b"%s)"])) % text
    if kind == "long":
        return b"(" + b"x" * draw(st.integers(1000, 20000)) + b")"
    if kind == "control":
        return bytes(draw(st.lists(st.sampled_from([0, 9, 11, 12, 13, 27, 127, 0xA0]), max_size=8)))
    return b""


@st.composite
def programs(draw, profile, box=((-300, 300),) * 3, special=0.05, junk=0.15, max_lines=25):
    lines = []
    for _ in range(draw(st.integers(0, max_lines))):
        r = draw(st.floats(0, 1))
        if r < junk:
            body = draw(junk_line())
        elif r < junk + 0.2:
            body = draw(st.sampled_from(MODAL)).encode()
        else:
            body = draw(motion_line(profile, box, special)).encode("latin-1")
        if draw(st.floats(0, 1)) < 0.15:
            body += b" (" + draw(st.text(max_size=12)).encode("utf-8", "replace").replace(b"\n", b"") + b")"
        lines.append(body + draw(st.sampled_from([b"\n", b"\n", b"\n", b"\r\n", b"\r", b"\n\n"])))
    data = b"".join(lines)
    if data and draw(st.booleans()):
        data = data.rstrip(b"\r\n")  # no final newline
    return data


@st.composite
def profile_and_program(draw, clean=False):
    """A profile's name and a program for it: half of them without values no controller takes."""
    name = draw(st.sampled_from(sorted(PROFILES)))
    special = 0.0 if clean else draw(st.sampled_from([0.0, 0.0, 0.01, 0.05]))
    return name, draw(programs(PROFILES[name], special=special, junk=draw(st.sampled_from([0.0, 0.1, 0.3]))))


# -- options ---------------------------------------------------------------------------------------
NUMERIC = {
    "--standoff": ["0", "6", "3.5", "-1", "1e9", "abc", "nan"],
    "--max-step": ["2", "30", "0", "90", "91", "inf"],
    "--max-tilt": ["30", "5", "0", "90", "-3"],
    "--pitch": ["0.5", "2", "0", "-1", "60", "x"],
    "--clearance": ["0", "0.5", "-0.1", "101"],
    "--bead-radius": ["0", "1", "0.3", "-1"],
    "--tip-allowance": ["1", "0", "5", "-2"],
    "--resolution": ["1", "2", "0.01", "11"],
    "--window": ["2000", "16", "15", "abc", "1.5"],
    "--deposit-codes": ["M3,M5", "M101,M103", "M3", "M3,M3", ","],
    "--head-tip": ["0,0,0", "0,0,1", "1,2", "0,0,nan"],
    "--head-axis": ["0,0,1", "1,0,0", "0,0,0"],
    "--strategy": ["epa", "graph", "best"],
    "--pivot": ["tip", "point", "middle"],
    "--device": ["cpu", "auto", "tpu"],
}


@st.composite
def option_args(draw):
    args = []
    for flag in draw(st.lists(st.sampled_from(sorted(NUMERIC)), max_size=5, unique=True)):
        values = NUMERIC[flag]
        valid = draw(st.floats(0, 1)) < 0.8  # the first two values of each are valid
        args += [flag, draw(st.sampled_from(values[:2] if valid else values))]
    return args


@pytest.fixture(scope="module")
def workdir():
    with tempfile.TemporaryDirectory(prefix="ncfix-props-") as folder:
        old = os.getcwd()
        os.chdir(folder)  # no ncfix.toml here: only the options given are read
        try:
            yield Path(folder)
        finally:
            os.chdir(old)


@pytest.fixture(autouse=True, scope="module")
def same_examples_everywhere(workdir):
    """No local constants in hypothesis's draws, and an empty cache folder of this module's own:
    the same examples, with the same outcomes, on every machine and in every run."""
    assert callable(providers._get_local_constants)  # fails loudly if hypothesis renames it
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(providers, "_get_local_constants", providers.Constants)
        patch.setenv("NCFIX_CACHE", str(workdir / "cache"))
        providers.CONSTANTS_CACHE.cache.clear()  # pools built with another test file's constants
        try:
            yield
        finally:
            providers.CONSTANTS_CACHE.cache.clear()


def any_program_without_a_head(workdir, case, check, quiet, via_stdin, to_file, other_machine):
    name, program = case
    src = workdir / "in.nc"
    src.write_bytes(program)
    out_path = workdir / "out.nc"
    if out_path.exists():
        out_path.unlink()
    argv = ["-", "--machine", other_machine or name] if via_stdin else [str(src), "--machine", other_machine or name]
    argv += (["--check"] if check else []) + (["-q"] if quiet else []) + (["-o", str(out_path)] if to_file else [])
    status, out, err, runtime = run_cli(argv, program if via_stdin else b"")
    if to_file:
        assert out == b""
        out = out_path.read_bytes() if out_path.exists() else b""
        assert status != 2 or not out_path.exists(), argv  # nothing written to -o on an error
    assert_honest(status, out, err, runtime, program, check=check, quiet=quiet, passthrough=True, argv=argv)
    assert not [p for p in workdir.iterdir() if p.name.endswith(".tmp")]


test_any_program_without_a_head, test_any_program_without_a_head_fast = both_runs(
    600, case=profile_and_program(), check=st.booleans(), quiet=st.booleans(), via_stdin=st.booleans(),
    to_file=st.booleans(), other_machine=st.sampled_from([None] * 4 + sorted(PROFILES)))(any_program_without_a_head)


def any_options_without_a_head(workdir, case, options, check):
    name, program = case
    argv = ["-", "--machine", name, "-q", *options] + (["--check"] if check else [])
    status, out, err, runtime = run_cli(argv, program)
    assert_honest(status, out, err, runtime, program, check=check, quiet=True, passthrough=True, argv=argv)


test_any_options_without_a_head, test_any_options_without_a_head_fast = both_runs(
    300, case=profile_and_program(clean=True), options=option_args(), check=st.booleans())(any_options_without_a_head)


# -- with a small head and plate -----------------------------------------------------------------
def small_head() -> trimesh.Trimesh:
    return trimesh.creation.revolve(np.array([[0.0, 0.0], [2.0, 1.5], [2.0, 10.0], [0.0, 10.0]]), sections=8)


@pytest.fixture(scope="module")
def meshes(workdir):
    head = workdir / "head.stl"
    small_head().export(head)
    plate = trimesh.creation.box([30.0, 30.0, 3.0])
    plate.apply_translation([0.0, 0.0, -1.5])
    part = workdir / "plate.stl"
    plate.export(part)
    return head, part


PLATE_BOX = ((-12, 12), (-12, 12), (-2, 8))


@st.composite
def head_case(draw):
    name = draw(st.sampled_from(["ijk", "ijk", "sinumerik-vector", "heidenhain-ln", "table-ac", "table-bc",
                                 "head-bc", "multiaxis-3dp-bc"]))
    program = draw(programs(PROFILES[name], PLATE_BOX, special=0.02, junk=0.05, max_lines=10))
    return name, program


def any_program_with_a_small_head(workdir, meshes, case, check, strategy, bead, pivot, step):
    name, program = case
    head, part = meshes
    argv = ["-", "--machine", name, "-q", "--head", str(head), "--part", str(part), "--pitch", "1",
            "--standoff", "2", "--strategy", strategy, "--bead-radius", bead, "--pivot", pivot, "--max-step", step]
    argv += ["--check"] if check else []
    status, out, err, runtime = run_cli(argv, program)
    assert_honest(status, out, err, runtime, program, check=check, quiet=True, passthrough=False, argv=argv)


test_any_program_with_a_small_head, test_any_program_with_a_small_head_fast = both_runs(
    100, case=head_case(), check=st.booleans(), strategy=st.sampled_from(["epa", "graph"]),
    bead=st.sampled_from(["0", "0.5"]), pivot=st.sampled_from(["tip", "point"]),
    step=st.sampled_from(["2", "30"]))(any_program_with_a_small_head)


# -- meshes ----------------------------------------------------------------------------------------
MESH_PROGRAM = b"G21 G90\nG1 X0 Y0 Z4 I0 J0 K1 F600\nG1 X5 Y0 Z4\nG1 X5 Y5 Z4 I0.2 J0 K0.98\nM30\n"


@st.composite
def mesh_bytes(draw):
    kind = draw(st.sampled_from(["hull", "hull", "box", "open", "flipped", "nan", "inf", "degenerate", "empty",
                                 "garbage", "huge", "tiny", "obj", "two"]))
    suffix = ".obj" if kind == "obj" else ".stl"
    if kind == "empty":
        return b"", suffix
    if kind == "garbage":
        return draw(st.binary(min_size=1, max_size=300)), suffix
    points = np.array(draw(st.lists(st.tuples(*[st.floats(-6, 6)] * 3), min_size=4, max_size=12)))
    size = draw(st.floats(0.5, 8))  # drawn whether used or not: what follows does not depend on qhull
    try:
        with np.errstate(all="ignore"):
            mesh = trimesh.convex.convex_hull(points)
    except Exception:  # flat or repeated points: no hull
        mesh = trimesh.creation.box([4.0, 4.0, 4.0])
    if kind == "box" or len(mesh.faces) < 4:
        mesh = trimesh.creation.box([size] * 3)
    vertices, faces = mesh.vertices.copy(), mesh.faces.copy()
    if kind == "open":
        faces = faces[1:]
    elif kind == "flipped":
        faces = faces[:, ::-1]
    elif kind in ("nan", "inf"):
        vertices[0, draw(st.integers(0, 2))] = np.nan if kind == "nan" else np.inf
    elif kind == "degenerate":
        faces = np.vstack([faces, [[0, 0, 1]]])
    elif kind == "huge":
        vertices *= 1e5
    elif kind == "tiny":
        vertices *= 1e-4
    elif kind == "two":
        vertices = np.vstack([vertices, vertices + 20.0])
        faces = np.vstack([faces, faces + len(mesh.vertices)])
    with np.errstate(all="ignore"):
        built = trimesh.Trimesh(vertices, faces, process=False)
        if kind == "obj":
            return trimesh.exchange.obj.export_obj(built).encode(), suffix
        if draw(st.booleans()):
            return trimesh.exchange.stl.export_stl_ascii(built).encode(), suffix
        return trimesh.exchange.stl.export_stl(built), suffix


def any_mesh(workdir, meshes, mesh, role, check, tip):
    data, suffix = mesh
    path = workdir / f"m{suffix}"
    path.write_bytes(data)
    head, part = meshes
    argv = ["-", "-q", "--pitch", "1", "--standoff", "2", "--check" if check else "--bead-radius=0.5"]
    argv += ["--head", str(path), "--part", str(part)] if role == "--head" else ["--head", str(head), "--part", str(path)]
    argv += ["--head-tip", tip] if tip and role == "--head" else []
    status, out, err, runtime = run_cli(argv, MESH_PROGRAM)
    assert_honest(status, out, err, runtime, MESH_PROGRAM, check=check, quiet=True, passthrough=False, argv=argv)


test_any_mesh, test_any_mesh_fast = both_runs(
    60, mesh=mesh_bytes(), role=st.sampled_from(["--head", "--part"]), check=st.booleans(),
    tip=st.sampled_from([None, "0,0,0", "0,0,-6"]))(any_mesh)
