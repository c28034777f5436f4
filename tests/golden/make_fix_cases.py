"""The golden correction cases: one colliding program per machine profile (tests/golden/fix_<profile>).

    python tests/golden/make_fix_cases.py   # write each case's input and case.toml, and meshes/wall_*.stl
    python tests/golden/regen.py fix_        # then (re)write what ncfix makes of them: review the diff!

A path of 2 mm blocks, the head vertical, 6 mm over the floor, with a wall beside it, so that
the head's 56 mm body runs into the wall for a few dozen blocks. ncfix tilts the head away from
the wall about the tip and back, within 2° a block. A machines (and the vector profiles) run
along X with the wall on the +Y side: they tilt with A alone. B machines run along Y with the wall
on the -X side: they tilt with B alone (no turn of C at the pole, which on a table-table machine
would swing the asymmetric head round in the part's frame).
Settings (``flags`` below): the sample head, the wall, no deposit model, the graph strategy (the
EPA strategy leaves a few ramp blocks of these cases unresolved).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
HEAD = "../../../samples/deposition_head.stl"  # from a case folder
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


def wall_name(y: bool) -> str:
    return "wall_y.stl" if y else "wall_x.stl"


def flags(profile) -> list[str]:
    return ["--machine", profile.name, "--head", HEAD, "--part", f"../meshes/{wall_name(along_y(profile))}",
            "--bead-radius", "0", "--strategy", "graph"]


def case_toml(profile) -> str:
    side = "a wall on the -X side of a path along Y" if along_y(profile) else "a wall on the +Y side of a path along X"
    return (f'about = "The {profile.name} profile: {side}, the head vertical; ncfix tilts it off the wall about '
            f'the tip and back (made by make_fix_cases.py)."\n'
            f"args = {json.dumps(flags(profile))}\n"
            "heavy = true\n")


def main() -> int:
    sys.path.insert(0, str(REPO))
    from ncfix.nc.post import post_program
    from ncfix.profiles import builtin_names, load_profile

    for y in (False, True):
        wall(y).export(HERE / "meshes" / wall_name(y), file_type="stl_ascii")
    for name in builtin_names():
        profile = load_profile(name)
        folder = HERE / f"fix_{name}"
        folder.mkdir(exist_ok=True)
        P, N = path(along_y(profile))
        program = "".join(post_program(profile, P, N, title=f"golden fix {name}")).encode("ascii")
        (folder / f"input{EXTENSIONS.get(profile.dialect, '.nc')}").write_bytes(program)
        (folder / "case.toml").write_text(case_toml(profile))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
