"""The golden correction cases: one colliding program per machine profile, and what ncfix makes of it.

    python tests/cases/fix/make_cases.py            # write the inputs (fix_<profile>.<ext>) and wall.stl
    python tests/cases/fix/make_cases.py --expected # also (re)write the expected outputs: review the diff!

A path of 2 mm blocks, the head vertical, 6 mm over the floor, with a wall beside it, so that
the head's 56 mm body runs into the wall for a few dozen blocks. ncfix tilts the head away from
the wall about the tip and back, within 2° a block. A machines (and the vector profiles) run
along X with the wall on the +Y side: they tilt with A alone. B machines run along Y with the wall
on the -X side: they tilt with B alone (no turn of C at the pole, which on a table-table machine
would swing the asymmetric head round in the part's frame).
Settings (SETTINGS below): the sample head, the wall, no deposit model, the graph strategy (the EPA
strategy leaves a few ramp blocks of these cases unresolved).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[2]
SETTINGS = {"head": str(REPO / "samples" / "deposition_head.stl"), "bead_radius": 0.0, "strategy": "graph"}
EXTENSIONS = {"sinumerik": ".mpf", "heidenhain": ".h"}


def along_y(profile) -> bool:
    """B machines run along Y (module doc)."""
    return "B" in profile.kinematics.letters


def path(y: bool) -> tuple[np.ndarray, np.ndarray]:
    s = np.arange(-90.0, 90.0 + 1e-9, 2.0)
    zero = np.zeros_like(s)
    P = np.stack([zero, s, zero] if y else [s, zero, zero], axis=1)
    return P, np.tile([0.0, 0.0, 1.0], (len(s), 1))


def wall(y: bool):
    """A wall 40 mm high, 20 mm long, its face 25 mm from the path (the body reaches 28)."""
    import trimesh

    if y:
        mesh = trimesh.creation.box(extents=(15.0, 20.0, 50.0))
        mesh.apply_translation((-32.5, 0.0, 15.0))  # x -40..-25
    else:
        mesh = trimesh.creation.box(extents=(20.0, 15.0, 50.0))
        mesh.apply_translation((0.0, 32.5, 15.0))  # y 25..40
    return mesh


def wall_path(y: bool) -> Path:
    return HERE / ("wall_y.stl" if y else "wall_x.stl")


def settings(profile) -> dict:
    return {**SETTINGS, "machine": profile.name, "part": [str(wall_path(along_y(profile)))]}


def case_files() -> list[tuple[str, Path]]:
    """(profile name, input path) of every built-in profile."""
    from ncfix.profiles import builtin_names, load_profile

    out = []
    for name in builtin_names():
        ext = EXTENSIONS.get(load_profile(name).dialect, ".nc")
        out.append((name, HERE / f"fix_{name}{ext}"))
    return out


def expected_path(src: Path) -> Path:
    return src.with_name(src.stem + ".expected" + src.suffix)


def main(argv: list[str] | None = None) -> int:
    sys.path.insert(0, str(REPO))
    from ncfix.nc.post import post_program
    from ncfix.profiles import load_profile

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--expected", action="store_true", help="also write the expected outputs")
    args = parser.parse_args(argv)
    for y in (False, True):
        wall(y).export(wall_path(y), file_type="stl_ascii")
    for name, src in case_files():
        profile = load_profile(name)
        P, N = path(along_y(profile))
        src.write_bytes("".join(post_program(profile, P, N, title=f"golden fix {name}")).encode("ascii"))
        if args.expected:
            import ncfix

            report = ncfix.process(src, expected_path(src), **settings(profile))
            print(f"{name:<22} colliding {report.summary['colliding_blocks_before']:>3}  changed "
                  f"{report.summary['changed_blocks']:>3}  unresolved {report.summary['unresolved_blocks']}  "
                  f"exit {report.exit_code}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
