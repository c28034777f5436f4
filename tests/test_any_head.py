"""Any head: revolved heads of 8 to 1,024 segments per ring (discs fan-triangulated or not), the
corpus heads and a torch with a side wire feeder, each fixed by both strategies on a wall sample
and a pocket sample the head hits. Every run finishes (never an exception) with every block freed
(exit 0: each wall reaches only 2 mm into the head, so a tilt clears it), and the exact reference
finds no collision in the output: at the end poses (with the beads laid before them) and along
the moves (against the parts)."""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

import ncfix
from conftest import CORPUS
from heads import revolved_head, torch_with_feeder, write_stl
from ncfix.geometry.frames import minimal_rotation
from ncfix.geometry.mesh import load_head
from ncfix.reference import ExactReference, label_program

STANDOFF = 2.0
STEP_MM = 5.0
PENETRATION_MM = 2.0  # how far each wall reaches into the head as programmed
# Coarse but honest: the checker is conservative at any pitch, θ = 10° keeps the ramps at 4 blocks.
SETTINGS = {"machine": "ijk", "standoff": STANDOFF, "pitch": 1.0, "max_step": 10.0, "deposit_codes": "M3,M5",
            "device": "cpu"}

CORPUS_HEADS = {
    # name: (path in the corpus, --head-tip, --head-axis)
    "extruderHead": ("multiaxis_3dp_motionplanning/extruderHead_converted.stl", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "extruderHead_original": ("multiaxis_3dp_motionplanning/extruderHead_original_converted.stl", (0.0, 0.0, 0.0),
                              (0.0, 0.0, 1.0)),
    # In its assembly's frame: the nozzle tip at (-4.4, -89.0, 12.5), the axis along +Y (MANIFEST.md).
    "e3d_v6": ("e3d_v6/e3d_v6.stl", (-4.4, -89.0, 12.5), (0.0, 1.0, 0.0)),
}
# Fast cells run by default, one per kind of head (a coarse ring, a fine ring with strip caps, the
# non-round corpus head, the torch), both samples and both strategies among them; the whole matrix
# is heavy.
REVOLVED = [(segments, caps) for segments in (8, 64, 128, 512, 1024) for caps in ("fan", "strip")]
HEADS = [f"revolved{s}-{c}" for s, c in REVOLVED] + ["revolved512-pointed", *CORPUS_HEADS, "torch"]
FAST = {("revolved8-fan", "wall", "epa"), ("revolved128-strip", "pocket", "graph"),
        ("extruderHead_original", "pocket", "graph"), ("torch", "wall", "graph")}


def _head(name: str, folder: Path) -> tuple[str, tuple, tuple]:
    """(STL path, tip, axis) of a head of the matrix."""
    if name in CORPUS_HEADS:
        rel, tip, axis = CORPUS_HEADS[name]
        path = CORPUS / rel
        if not path.exists():
            pytest.skip(f"corpus file {path} is absent")
        return str(path), tip, axis
    if name == "torch":
        mesh = torch_with_feeder()
    elif name.endswith("-pointed"):
        mesh = revolved_head(int(name[len("revolved"):].split("-")[0]), "fan", pointed=True)
    else:
        segments, caps = name[len("revolved"):].split("-")
        mesh = revolved_head(int(segments), caps)
    return str(write_stl(mesh, folder / f"{name}.stl")), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0)


def _reach(head: trimesh.Trimesh, direction) -> float:
    return float((np.asarray(head.vertices) @ np.asarray(direction, dtype=np.float64)).max())


def _program(points: list[tuple[float, float, float]], title: str) -> bytes:
    """An ijk program: rapid above the first point, plunge, M3, the points at 1200 mm/min, M5, lift."""
    x0, y0, _ = points[0]
    lines = ["%", f"({title})", "G21 G90 G94", f"G0 X{x0:.3f} Y{y0:.3f} Z20.000 I0 J0 K1"]
    lines.append(f"G1 X{x0:.3f} Y{y0:.3f} Z{points[0][2]:.3f} F1200")
    lines.append("M3")
    lines += [f"G1 X{x:.3f} Y{y:.3f} Z{z:.3f}" for x, y, z in points[1:]]
    x1, y1, _ = points[-1]
    lines += ["M5", f"G0 X{x1:.3f} Y{y1:.3f} Z20.000", "M30", "%"]
    return ("\n".join(lines) + "\n").encode("ascii")


def wall_sample(head: trimesh.Trimesh, folder: Path) -> tuple[Path, Path]:
    """A straight pass along X; beside it on +Y a wall 30 mm long whose face is 2 mm inside the
    head's reach toward it."""
    face = _reach(head, (0, 1, 0)) - PENETRATION_MM
    wall = trimesh.creation.box(bounds=[(-15.0, face, -10.0), (15.0, face + 10.0, 130.0)])
    xs = np.arange(-50.0, 50.0 + 1e-9, STEP_MM)
    program = folder / "wall.nc"
    program.write_bytes(_program([(x, 0.0, 0.0) for x in xs], "wall sample"))
    return program, write_stl(wall, folder / "wall.stl")


def pocket_sample(head: trimesh.Trimesh, folder: Path, step_mm: float = STEP_MM) -> tuple[Path, Path]:
    """Along the floor of a pocket: +X beside its +Y wall into the corner, then -Y beside its +X
    wall, points ``step_mm`` apart; both walls 2 mm inside the head's reach toward them, the other
    walls clear of it."""
    import manifold3d

    fy, fx = _reach(head, (0, 1, 0)) - PENETRATION_MM, _reach(head, (1, 0, 0)) - PENETRATION_MM
    bx, by = -40.0 - _reach(head, (-1, 0, 0)) - 15.0, -40.0 - _reach(head, (0, -1, 0)) - 15.0
    block = trimesh.creation.box(bounds=[(bx - 15.0, by - 15.0, -15.0), (fx + 15.0, fy + 15.0, 70.0)])
    hole = trimesh.creation.box(bounds=[(bx, by, 0.0), (fx, fy, 80.0)])

    def solid(mesh):
        return manifold3d.Manifold(manifold3d.Mesh64(vert_properties=np.asarray(mesh.vertices, dtype=np.float64),
                                                     tri_verts=np.asarray(mesh.faces, dtype=np.uint64)))

    cut = (solid(block) - solid(hole)).to_mesh64()
    pocket = trimesh.Trimesh(np.asarray(cut.vert_properties[:, :3]), np.asarray(cut.tri_verts, dtype=np.int64))
    s = np.arange(-40.0, 1e-9, step_mm)
    points = [(x, 0.0, 0.0) for x in s] + [(0.0, y, 0.0) for y in s[-2::-1]]
    program = folder / "pocket.nc"
    program.write_bytes(_program(points, "pocket sample"))
    return program, write_stl(pocket, folder / "pocket.stl")


SAMPLES = {"wall": wall_sample, "pocket": pocket_sample}


def _sweep_hits(data: bytes, ref: ExactReference, spacing_mm: float = 0.5) -> set[int]:
    """Lines whose move (from the motion block before) meets a part at some pose along it: poses
    at most ``spacing_mm`` of tip travel and 0.5° apart, the tool vector turning on the great
    circle."""
    from ncfix.nc.modal import Interpreter
    from ncfix.profiles import load_profile

    profile = load_profile("ijk")
    chunk = Interpreter(profile).feed_chunk(data.splitlines(keepends=True), 1)
    rows = np.nonzero(chunk.motion >= 0)[0]
    P, N, _ = profile.kinematics.forward(chunk.words[rows], tcp=True)
    hits = set()
    for k in range(1, len(rows)):
        a, b = N[k - 1], N[k]
        angle = float(np.arccos(np.clip(a @ b, -1.0, 1.0)))
        steps = max(1, int(np.ceil(max(np.linalg.norm(P[k] - P[k - 1]) / spacing_mm, np.degrees(angle) / 0.5))))
        for t in np.linspace(0.0, 1.0, steps + 1)[1:-1]:
            n = a if angle < 1e-12 else (np.sin((1 - t) * angle) * a + np.sin(t * angle) * b) / np.sin(angle)
            c = P[k - 1] + t * (P[k] - P[k - 1]) + STANDOFF * n
            if ref.collides(c, minimal_rotation(n[None])[0]):
                hits.add(int(chunk.first_lineno + rows[k]))
                break
    return hits


def run_cell(head_name: str, sample: str, strategy: str, folder: Path) -> dict:
    """Fix the sample with the head and strategy; check the output exactly; return figures."""
    head_path, tip, axis = _head(head_name, folder)
    head = load_head(head_path, tip, axis).mesh
    program, part = SAMPLES[sample](head, folder)
    out = io.BytesIO()
    started = time.perf_counter()
    report = ncfix.process(program, out, head=head_path, head_tip=tip, head_axis=axis, part=[str(part)],
                           strategy=strategy, **SETTINGS)
    seconds = time.perf_counter() - started
    assert report.exit_code in (0, 1)
    found = report.summary["colliding_blocks_before"]
    assert found > 0, "the sample must make the head collide"
    unresolved = {u["line"] for u in report.unresolved}
    assert (report.exit_code == 1) == bool(unresolved)
    assert not unresolved, f"left colliding: lines {sorted(unresolved)}"
    output = folder / f"out-{sample}-{strategy}.nc"
    output.write_bytes(out.getvalue())
    ends, sweeps = exact_collisions(output, head, {part.name: trimesh.load(part)})
    assert not ends, f"the exact reference finds the output's end poses colliding: lines {sorted(ends)}"
    assert not sweeps, f"the exact reference finds the output's moves colliding: lines {sorted(sweeps)}"
    return {"found": found, "unresolved": len(unresolved), "seconds": seconds}


def exact_collisions(program: Path, head: trimesh.Trimesh, parts: dict) -> tuple[set[int], set[int]]:
    """The exact reference's answer on a program of the matrix (bench/run times it on a fix's
    output): the lines whose end pose collides (parts and the beads laid before it), and the
    lines whose move meets a part along the way."""
    ends = label_program(str(program), "ijk", head, parts, standoff_mm=STANDOFF, deposit_codes=("M3", "M5"))
    return {line for line, _ in ends}, _sweep_hits(program.read_bytes(), ExactReference(head, parts))


CELLS = [pytest.param(head, sample, strategy,
                      marks=() if (head, sample, strategy) in FAST else pytest.mark.heavy,
                      id=f"{head}-{sample}-{strategy}")
         for head in HEADS for sample in SAMPLES for strategy in ("epa", "graph")]


@pytest.mark.parametrize("head_name, sample, strategy", CELLS)
def test_any_head_is_fixed_or_reported(head_name, sample, strategy, tmp_path):
    figures = run_cell(head_name, sample, strategy, tmp_path)
    print(f"{head_name} {sample} {strategy}: {figures}")
