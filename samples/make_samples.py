"""Make the sample mold, head and bathtub toolpaths (deterministic; the STL outputs are committed).

    /work/venv/bin/python samples/make_samples.py          # writes the two STL files
    /work/venv/bin/python samples/make_samples.py --stats  # also prints collision fractions

recreated_mold.stl: a bathtub-like mold, 200 x 100 x 60 mm: a tub with a flat floor at z = 20,
steep side walls and gentler end walls, a flat rim around the opening at z = 60.
deposition_head.stl: nozzle cone (tip at the origin, axis +Z), a 56 mm wide body from z = 25,
and a feeder box on the +X side (the head is not rotationally symmetric).
The toolpath spirals down the tub's inner walls and then spirals inward over the floor.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

# Cavity: a rounded rectangle at the floor, scaled linearly up to the opening.
FLOOR_Z_MM = 20.0
TOP_Z_MM = 60.0
FLOOR_SIZE_MM = (110.0, 50.0)
OPENING_SIZE_MM = (176.0, 80.0)
FLOOR_CORNER_MM = 12.0
STANDOFF_MM = 6.0
# Programmed tool vectors follow the surface normal, tilted at most this far from vertical.
PROGRAM_TILT_DEG = 30.0


def _rounded_rect(width: float, depth: float, corner: float, segments: int = 48):
    import manifold3d as m3d

    core = m3d.CrossSection.square((width - 2 * corner, depth - 2 * corner), center=True)
    return core.offset(corner, m3d.JoinType.Round, circular_segments=segments)


def _slab(cs, z0: float, z1: float):
    import manifold3d as m3d

    return m3d.Manifold.extrude(cs, z1 - z0).translate((0.0, 0.0, z0))


def _to_trimesh(solid):
    import trimesh

    mesh = solid.to_mesh()
    out = trimesh.Trimesh(
        np.asarray(mesh.vert_properties)[:, :3].astype(np.float64),
        np.asarray(mesh.tri_verts).astype(np.int64),
        process=True,
    )
    assert out.is_watertight and out.body_count == 1 and out.volume > 0
    return out


def build_mold():
    """The bathtub mold as a closed trimesh (mm, Z up)."""
    import manifold3d as m3d

    depth = TOP_Z_MM - FLOOR_Z_MM
    floor_cs = _rounded_rect(*FLOOR_SIZE_MM, FLOOR_CORNER_MM)
    scale = (OPENING_SIZE_MM[0] / FLOOR_SIZE_MM[0], OPENING_SIZE_MM[1] / FLOOR_SIZE_MM[1])
    # Extend the cavity 1 mm above the rim with the same slope so the cut is clean.
    over = 1.0
    scale_over = tuple(1.0 + (s - 1.0) * (depth + over) / depth for s in scale)
    cavity = m3d.Manifold.extrude(floor_cs, depth + over, scale_top=scale_over).translate(
        (0.0, 0.0, FLOOR_Z_MM)
    )
    outer = m3d.Manifold.batch_hull(
        [
            _slab(_rounded_rect(150.0, 66.0, 20.0), 0.0, 0.1),
            _slab(_rounded_rect(192.0, 96.0, 24.0), 51.9, 52.0),
        ]
    )
    rim = _slab(_rounded_rect(200.0, 100.0, 26.0), 52.0, TOP_Z_MM)
    return _to_trimesh((outer + rim) - cavity)


def build_head():
    """The sample deposition head as a closed trimesh: tip at the origin, axis +Z."""
    import manifold3d as m3d

    nozzle = m3d.Manifold.cylinder(25.0, 0.5, 7.0, circular_segments=48)
    heater = m3d.Manifold.cube((22.0, 22.0, 10.0), center=True).translate((0.0, 0.0, 22.0))
    body = _slab(_rounded_rect(56.0, 56.0, 6.0, 24), 25.0, 110.0)
    chamfer = m3d.Manifold.batch_hull(
        [_slab(_rounded_rect(30.0, 30.0, 4.0, 24), 17.0, 17.1), _slab(_rounded_rect(56.0, 56.0, 6.0, 24), 25.0, 25.1)]
    )
    feeder = m3d.Manifold.cube((26.0, 20.0, 55.0)).translate((26.0, -10.0, 40.0))
    tube = m3d.Manifold.cylinder(30.0, 4.0, circular_segments=32).translate((40.0, 0.0, 95.0))
    return _to_trimesh(nozzle + heater + body + chamfer + feeder + tube)


def _opening_scale(z: np.ndarray) -> np.ndarray:
    """Cavity half sizes (n, 2) mm at heights z (n,), linear between floor and opening."""
    t = (np.asarray(z) - FLOOR_Z_MM) / (TOP_Z_MM - FLOOR_Z_MM)
    floor = np.array(FLOOR_SIZE_MM)
    top = np.array(OPENING_SIZE_MM)
    return 0.5 * (floor + (top - floor) * t[:, None])


def _rounded_rect_points(half: np.ndarray, corner: np.ndarray, phase: np.ndarray) -> np.ndarray:
    """Points (n, 2) on rounded rectangles (half sizes (n, 2), corner radii (n,)) at phase in [0, 1).

    The walk starts at the lower end of the +X side and runs counter-clockwise.
    """
    n = len(phase)
    hx, hy = half[:, 0] - corner, half[:, 1] - corner
    centres = np.stack(
        [np.stack(xy, axis=1) for xy in ((hx, -hy), (hx, hy), (-hx, hy), (-hx, -hy))], axis=1
    )  # (n, 4, 2)
    arc = 0.5 * np.pi * corner
    lengths = np.stack([2 * hy, arc, 2 * hx, arc, 2 * hy, arc, 2 * hx, arc], axis=1)
    cum = np.cumsum(lengths, axis=1)
    s = phase * cum[:, -1]
    seg = np.minimum((s[:, None] >= cum).sum(axis=1), 7)
    rows = np.arange(n)
    u = (s - (cum[rows, seg] - lengths[rows, seg])) / np.maximum(lengths[rows, seg], 1e-12)
    q = seg // 2
    a = centres[rows, q]
    b = centres[rows, (q + 1) % 4]
    side_angle = 0.5 * np.pi * q
    on_side = seg % 2 == 0
    angle = np.where(on_side, side_angle, side_angle + 0.5 * np.pi * u)
    base = np.where(on_side[:, None], a + (b - a) * u[:, None], b)
    return base + corner[:, None] * np.stack([np.cos(angle), np.sin(angle)], axis=1)


def _spiral(n_dense: int = 40_000) -> np.ndarray:
    """Dense spiral on the cavity surface (n_dense, 3): down the walls, then in over the floor."""
    wall_turns, floor_turns = 8, 4
    u = np.linspace(0.0, wall_turns + floor_turns, n_dense, endpoint=False)
    phase = u % 1.0
    pts = np.zeros((n_dense, 3))
    wall = u < wall_turns
    z = TOP_Z_MM - 2.0 - (TOP_Z_MM - 2.0 - FLOOR_Z_MM - 0.5) * (u[wall] / wall_turns)
    half = _opening_scale(z)
    corner = FLOOR_CORNER_MM * half[:, 1] / (0.5 * FLOOR_SIZE_MM[1])
    pts[wall, :2] = _rounded_rect_points(half, corner, phase[wall])
    pts[wall, 2] = z
    f = ~wall
    inset = 8.0 + 12.0 * (u[f] - wall_turns) / floor_turns
    half = 0.5 * np.array(FLOOR_SIZE_MM) - inset[:, None]
    corner = np.maximum(FLOOR_CORNER_MM - inset, 1.0)
    pts[f, :2] = _rounded_rect_points(half, corner, phase[f])
    pts[f, 2] = FLOOR_Z_MM
    return pts


def bathtub_path(n: int, mold=None) -> tuple[np.ndarray, np.ndarray]:
    """The bathtub workload: n toolpath points on the mold's inner surface and their tool vectors.

    returns P : (n, 3) float64 workpiece mm, on the mold surface;
            N : (n, 3) float64 unit tool vectors (surface normal, tilted at most
            PROGRAM_TILT_DEG from vertical; vertical on the floor)
    """
    import trimesh

    mold = build_mold() if mold is None else mold
    dense = _spiral()
    step = np.linalg.norm(np.diff(dense, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(step)])
    targets = np.linspace(0.0, s[-1], n)
    approx = np.stack([np.interp(targets, s, dense[:, k]) for k in range(3)], axis=1)
    points, _, face = trimesh.proximity.closest_point(mold, approx)
    normals = np.asarray(mold.face_normals[face])
    normals = _limit_tilt(normals, PROGRAM_TILT_DEG)
    return points, normals


def _limit_tilt(n: np.ndarray, max_deg: float) -> np.ndarray:
    z = np.array([0.0, 0.0, 1.0])
    tilt = np.arccos(np.clip(n @ z, -1.0, 1.0))
    horiz = n.copy()
    horiz[:, 2] = 0.0
    norm = np.linalg.norm(horiz, axis=1, keepdims=True)
    horiz = np.divide(horiz, norm, out=np.zeros_like(horiz), where=norm > 1e-12)
    t = np.minimum(tilt, np.radians(max_deg))
    out = np.cos(t)[:, None] * z + np.sin(t)[:, None] * horiz
    return out / np.linalg.norm(out, axis=1, keepdims=True)


# Deposition (arc, laser, extruder) on and off in the bathtub programs, as a wire-arc post writes it.
DEPOSIT_CODES = ("M3", "M5")
# The bathtub programs in three dialects: (file suffix, machine profile).
DIALECTS = (("", "ijk", ".nc"), ("_table_ac", "table-ac", ".nc"), ("_sinumerik", "sinumerik-vector", ".mpf"))


def write_programs(n_points: tuple[int, ...] = (273, 5000), out: Path = HERE) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Post the bathtub workloads in every dialect of DIALECTS; returns the path arrays by point count."""
    from ncfix.nc.post import post_program
    from ncfix.profiles import load_profile

    mold = build_mold()
    paths = {}
    for n in n_points:
        p, n_vec = bathtub_path(n, mold)
        paths[n] = (p, n_vec)
        floor_start = int(np.argmax(p[:, 2] <= FLOOR_Z_MM + 1e-6))
        notes = [(0, "spiral down the tub walls"), (floor_start, "spiral in over the floor")]
        for suffix, machine, ext in DIALECTS:
            lines = post_program(load_profile(machine), p, n_vec, title=f"bathtub {n}", number=n, comments=notes,
                                 deposit_codes=DEPOSIT_CODES)
            (out / f"bathtub_{n}{suffix}{ext}").write_bytes("".join(lines).encode("ascii"))
    return paths


# The deposit workload: a wall printed in layers, then a bead laid beside it. Nothing but the
# printed wall is in the head's way (no part mesh), so only the deposit model can see it.
WALL_LAYERS = 20
WALL_HALF_LENGTH_MM = 20.0
LAYER_MM = 1.0
SECOND_BEAD_Y_MM = 4.0


def deposit_program() -> str:
    """The deposit workload as an ijk program with absolute E words (M82)."""
    out = ["%", "O0100 (DEPOSIT WALL)", "(A WALL PRINTED IN LAYERS, THEN A BEAD LAID 4 MM BESIDE IT)",
           "N10 G21 G90 G94 G17", "N20 G43.5 H1", "M82", "G92 E0"]
    e = 0.0
    xs = np.arange(-WALL_HALF_LENGTH_MM, WALL_HALF_LENGTH_MM + 1e-9, 2.0)
    for layer in range(WALL_LAYERS):
        z = 0.5 + layer * LAYER_MM
        row = xs if layer % 2 == 0 else xs[::-1]
        out.append(f"(LAYER {layer + 1})")
        out.append(f"G0 X{row[0]:.3f} Y0.000 Z{z + 5:.3f} I0. J0. K1.")
        out.append(f"G1 Z{z:.3f} F600")
        for x in row[1:]:
            e += 0.1
            out.append(f"G1 X{x:.3f} Y0.000 Z{z:.3f} E{e:.3f} F1200")
        out.append(f"G0 Z{z + 5:.3f}")
    out.append("(SECOND BEAD, BESIDE THE WALL)")
    out.append(f"G0 X-36.000 Y{SECOND_BEAD_Y_MM:.3f} Z5.500")
    out.append("G1 Z0.500 F600")
    for x in np.arange(-34.0, 36.0 + 1e-9, 2.0):
        e += 0.1
        out.append(f"G1 X{x:.3f} Y{SECOND_BEAD_Y_MM:.3f} Z0.500 E{e:.3f} F1200")
    out += ["G0 Z30.000", "G49", "M30", "%"]
    return "\n".join(out) + "\n"


def write_deposit_program(out: Path = HERE) -> None:
    (out / "deposit_wall.nc").write_bytes(deposit_program().encode("ascii"))


# What the exact reference says about each sample: (file, machine, parts).
SAMPLES = (
    *((f"bathtub_{n}{suffix}{ext}", machine, ("recreated_mold.stl",), DEPOSIT_CODES)
      for n in (273, 5000) for suffix, machine, ext in DIALECTS),
    ("deposit_wall.nc", "ijk", (), None),
)


def reference_labels(name: str, machine: str, parts: tuple[str, ...], deposit_codes=None,
                     **kwargs) -> list[tuple[int, list[str]]]:
    """(line, bodies) of each block of a sample that collides at its programmed orientation."""
    import trimesh

    from ncfix.reference import label_program

    head = trimesh.load(HERE / "deposition_head.stl")
    meshes = {part: trimesh.load(HERE / part) for part in parts}
    return label_program(str(HERE / name), machine, head, meshes, standoff_mm=STANDOFF_MM,
                         deposit_codes=deposit_codes, **kwargs)


def unfixable_blocks(name: str, machine: str, parts: tuple[str, ...], deposit_codes=None,
                     max_tilt_deg: float = 30.0) -> tuple[int, list[int]]:
    """(colliding blocks, lines of those no tilt about the tip within max_tilt_deg frees).

    Exact reference against the parts and the beads laid before each block (as reference_labels).
    """
    import trimesh

    from ncfix.geometry.frames import rotation_from_z
    from ncfix.nc.modal import Interpreter
    from ncfix.profiles import load_profile
    from ncfix.reference import ExactReference, bead_centres

    head = trimesh.load(HERE / "deposition_head.stl")
    ref = ExactReference(head, {part: trimesh.load(HERE / part) for part in parts})
    profile = load_profile(machine)
    with open(HERE / name, "rb") as handle:
        chunk = Interpreter(profile, name, deposit_codes).feed_chunk(handle.readlines(), 1)
    moving = np.flatnonzero(chunk.motion >= 0)
    p, n, _ = profile.kinematics.forward(chunk.words[moving])
    beads = np.zeros((0, 3))
    previous = None
    colliding, unfixable = 0, []
    for row, i in enumerate(moving):
        if chunk.motion[i] >= 1 and chunk.deposit_on[i] == 1 and previous is not None:
            beads = np.vstack([beads, bead_centres(previous, p[row], 0.25)])
        previous = p[row]
        tip = p[row] + STANDOFF_MM * n[row]

        def free(vector: np.ndarray) -> bool:
            rot = rotation_from_z(vector)
            return not ref.collides(tip, rot) and not (len(beads) and ref.bead_collides(tip, rot, beads, 1.0))

        if free(n[row]):
            continue
        colliding += 1
        if not any(free(v) for v in _cone(n[row], max_tilt_deg)):
            unfixable.append(int(i) + 1)
    return colliding, unfixable


def label_counts(labels: list[tuple[int, list[str]]]) -> tuple[int, int, int]:
    """(colliding blocks, blocks hitting a part, blocks hitting only deposited material)."""
    parts = sum(any(b.startswith("part:") for b in bodies) for _, bodies in labels)
    deposit_only = sum(bodies == ["deposit"] for _, bodies in labels)
    return len(labels), parts, deposit_only


def labels_markdown(all_labels: dict[str, list[tuple[int, list[str]]]]) -> str:
    """The reference-label table and line lists of samples/README.md."""
    machines = {name: machine for name, machine, _, _ in SAMPLES}
    rows = ["| sample | machine | colliding blocks | hitting the mold | hitting only deposit |", "|---|---|---|---|---|"]
    for name, labels in all_labels.items():
        total, parts, deposit_only = label_counts(labels)
        rows.append(f"| `{name}` | `{machines[name]}` | {total} | {parts} | {deposit_only} |")
    rows.append("")
    rows.append("Colliding lines (1-based line numbers of the file):")
    rows.append("")
    for name, labels in all_labels.items():
        if "5000" not in name:
            rows.append(f"- `{name}`: {', '.join(str(line) for line, _ in labels)}")
    return "\n".join(rows)


def collision_stats(n: int, max_tilt_deg: float = 30.0) -> dict[str, float]:
    """Collision fraction at the programmed orientation, and whether each is fixable by a tilt."""
    from ncfix.geometry.frames import rotation_from_z
    from ncfix.reference import ExactReference

    mold, head = build_mold(), build_head()
    ref = ExactReference(head, {"mold": mold})
    p, n_vec = bathtub_path(n, mold)
    tips = p + STANDOFF_MM * n_vec
    hit = np.array([ref.collides(c, rotation_from_z(v)) for c, v in zip(tips, n_vec)])
    unfixable = 0
    for i in np.nonzero(hit)[0]:
        if not any(ref.collides(tips[i], rotation_from_z(v)) is False for v in _cone(n_vec[i], max_tilt_deg)):
            unfixable += 1
    return {"points": n, "colliding": int(hit.sum()), "fraction": float(hit.mean()), "unfixable": unfixable}


def _cone(axis: np.ndarray, max_deg: float, rings: int = 6, per_ring: int = 24) -> list[np.ndarray]:
    """Directions within max_deg of axis, nearest first."""
    from ncfix.geometry.frames import rotation_from_z

    r = rotation_from_z(axis)
    out = []
    for k in range(1, rings + 1):
        t = np.radians(max_deg) * k / rings
        for j in range(per_ring):
            phi = 2 * np.pi * j / per_ring
            out.append(r @ np.array([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)]))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stats", action="store_true", help="print collision fractions")
    parser.add_argument("--labels", action="store_true", help="print the exact reference labels of every sample")
    args = parser.parse_args(argv)
    build_mold().export(HERE / "recreated_mold.stl")
    build_head().export(HERE / "deposition_head.stl")
    write_programs()
    write_deposit_program()
    if args.stats:
        for n in (273, 5000):
            print(collision_stats(n))
    if args.labels:
        print(labels_markdown({name: reference_labels(name, machine, parts, codes)
                               for name, machine, parts, codes in SAMPLES}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
