"""Benchmark of the collision checker (not a test): prints a table, medians over --runs runs.

    /work/venv/bin/python bench/check.py                 # 273 / 5,000 bathtub, 10k / 100k / 1M clean
    /work/venv/bin/python bench/check.py --sizes 10000 --runs 3

Bathtub workloads (samples/, ijk profile, mold part, deposit model on): time per stage (load,
head model, grids, check, report), peak RSS, and the exact reference on the same poses in the
same run: ``exact`` is the exact reference doing the checker's job on every pose the checker
covers (end poses and sweep samples at the pitch; timed on up to 3,000 of them and scaled): coal
against the mold (ExactReference.collides, ``exact parts``) plus the beads that pose sees
(ExactReference.bead_collides on the beads within the head's reach, found with a k-d tree). Its
ratio to ``check`` is the speed-up; ``labels`` is the reference's own labelling of the program
(reference.label_program: end poses only, mold and beads; 273 points only, it is slow). Clean workloads: generated layered prints (100 x 100 mm, 2 mm line
spacing, 1 mm blocks, 1.5 mm layers, vertical head) on a slab, deposit model on (M3 after the plunge to the first point, --deposit-codes M3,M5),
nothing collides; blocks/s of the whole check stage and peak RSS. Each workload runs in its own process
so that its peak memory is its own.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "samples"
sys.path.insert(0, str(SAMPLES))


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _clean_points(blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """A layered raster print: ``blocks`` points 1 mm apart, 2 mm between lines, 1.5 mm layers."""
    per_line, lines_per_layer = 100, 50
    i = np.arange(blocks)
    step = i % per_line
    line = (i // per_line) % lines_per_layer
    layer = i // (per_line * lines_per_layer)
    x = np.where(line % 2 == 0, step, per_line - 1 - step) - 50.0
    y = line * 2.0 - 50.0
    z = layer * 1.5
    return np.stack([x, y, z], axis=1).astype(np.float64), np.tile([0.0, 0.0, 1.0], (blocks, 1))


def write_clean(program: Path, blocks: int, piece: int = 200_000) -> Path:
    """The clean layered print (``_clean_points``) posted for the ijk profile as one program, in
    pieces of ``piece`` points: M3 after the plunge to the first point, the retract (straight up
    from the last point) and the end after the last piece."""
    from ncfix.nc.post import post_program
    from ncfix.profiles import load_profile

    profile = load_profile("ijk")
    with open(program, "w") as f:
        tail: list[str] = []
        for a in range(0, blocks, piece):
            P, N = _clean_points(min(blocks, a + piece))
            lines = list(post_program(profile, P[a:], N[a:], title="bench"))
            last = max(i for i, line in enumerate(lines) if " X" in line)  # the retract
            if a:  # the body only (not the approach nor the retract), then this piece's retract
                tail = [lines[last]] + tail[1:]
                lines = [line for line in lines if line.startswith("N") and " X" in line][1:-1]
            else:  # deposit from the first point on (M3), not on the plunge to it
                first = next(i for i, line in enumerate(lines) if " G1 " in line)
                lines.insert(first + 1, "M3\n")
                lines, tail = lines[:last + 1], lines[last + 1:]
            f.writelines(lines)
        f.writelines(tail)
    return program


def one(kind: str, size: int) -> dict:
    """One workload in this process -> timings (s), poses, blocks, peak RSS (MB)."""
    t0 = time.perf_counter()
    import torch  # noqa: F401  (import time is not the checker's)

    from ncfix.collision.checker import Checker
    from ncfix.collision.stage import CheckStage
    from ncfix.collision.head import build_head_model
    from ncfix.config import Options
    from ncfix.geometry.mesh import load_head, load_mesh
    from ncfix.nc.modal import Interpreter
    from ncfix.nc.post import post_program
    from ncfix.pipeline import read_chunks
    from ncfix.profiles import load_profile
    from ncfix.report import Report

    profile = load_profile("ijk")
    out: dict = {"import": time.perf_counter() - t0}
    tmp = Path(tempfile.mkdtemp())
    if kind == "bathtub":
        from make_samples import bathtub_path

        t = time.perf_counter()
        head = load_head(SAMPLES / "deposition_head.stl").mesh
        part = load_mesh(SAMPLES / "recreated_mold.stl", "part").mesh
        out["load"] = time.perf_counter() - t
        P, N = bathtub_path(size, part)
        program = tmp / "bathtub.nc"
        with open(program, "w") as f:
            f.writelines(post_program(profile, P, N, title="bench"))
        parts = [("part:recreated_mold.stl", part, True)]
    else:
        import trimesh

        t = time.perf_counter()
        head = load_head(SAMPLES / "deposition_head.stl").mesh
        part = trimesh.creation.box(extents=(120.0, 120.0, 5.0))
        part.apply_translation((0.0, 0.0, -3.5))
        out["load"] = time.perf_counter() - t
        program = write_clean(tmp / "clean.nc", size)
        parts = [("part:slab", part, True)]
    options = Options(head="head.stl", check=True, device="cpu",
                      deposit_codes=("M3", "M5") if kind == "clean" else None)
    t = time.perf_counter()
    model = build_head_model(head, options.pitch)
    out["head model"] = time.perf_counter() - t
    t = time.perf_counter()
    checker = Checker(head, model, parts, pitch_mm=options.pitch, bead_radius_mm=options.bead_radius,
                      tip_allowance_mm=options.tip_allowance, device="cpu")
    out["grids"] = time.perf_counter() - t

    recorded: list[tuple[np.ndarray, np.ndarray]] = []
    report = Report(input=str(program), machine=profile.name, options=options)
    stage = CheckStage(checker, profile, options, report)
    if kind == "bathtub":
        original = stage.path.check

        def recording(moves, store, seq0, **kw):
            hits, seq = original(moves, store, seq0, **kw)
            recorded.append((hits.C.copy(), hits.R.copy()))
            return hits, seq

        stage.path.check = recording  # type: ignore[method-assign]
        laid: list[tuple[np.ndarray, np.ndarray]] = []
        original_beads = stage.path._beads

        def beads(*args):
            pts, seq = original_beads(*args)
            laid.append((pts.copy(), seq.copy()))
            return pts, seq

        stage.path._beads = beads  # type: ignore[method-assign]
    t = time.perf_counter()
    blocks = 0
    with open(program, "rb") as src:
        for chunk in read_chunks(src, Interpreter(profile, str(program), options.deposit_codes)):
            for c in stage.push(chunk):
                report.count(c)
        stage.flush()
    out["check"] = time.perf_counter() - t
    blocks = report.summary["motion_blocks"]
    t = time.perf_counter()
    json.dumps(report.to_json())
    out["report"] = time.perf_counter() - t
    out["blocks"] = blocks
    out["poses"] = checker.stats.poses
    out["colliding"] = report.summary["colliding_blocks_before"]
    out["beads"] = stage.store.count
    out["store_mb"] = stage.store.nbytes / 2**20
    out["peak_mb"] = _rss_mb()
    if recorded:
        C = np.concatenate([c for c, _ in recorded])
        R = np.concatenate([r for _, r in recorded])
        pick = np.random.default_rng(0).choice(len(C), size=min(3000, len(C)), replace=False)
        from scipy.spatial import cKDTree

        from ncfix.reference import ExactReference

        ref = ExactReference(checker.head, {p.name: p.mesh for p in checker.exact.parts},
                             tip_allowance_mm=checker.tip_allowance_mm,
                             open_parts={p.name for p in checker.exact.parts if not p.closed})
        t = time.perf_counter()
        for i in pick:
            ref.collides(C[i], R[i])
        out["exact parts"] = (time.perf_counter() - t) * len(C) / len(pick)
        B = np.concatenate([b for b, _ in laid]) if laid else np.zeros((0, 3))
        bseq = np.concatenate([q for _, q in laid]) if laid else np.zeros(0, dtype=np.int64)
        reach = checker.rho_mm + options.bead_radius
        t = time.perf_counter()
        tree = cKDTree(B) if len(B) else None
        for i in pick:  # samples are numbered from 0 in program order: seq = index
            if tree is None:
                continue
            near = np.asarray(tree.query_ball_point(C[i], reach), dtype=np.int64)
            near = near[bseq[near] <= i]
            ref.bead_collides(C[i], R[i], B[near], options.bead_radius)
        out["exact"] = out["exact parts"] + (time.perf_counter() - t) * len(C) / len(pick)
        if size <= 1000:
            from ncfix.reference import label_program

            t = time.perf_counter()
            label_program(str(program), "ijk", head, {"recreated_mold.stl": part})
            out["labels"] = time.perf_counter() - t
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--sizes", default="273,5000,10000,100000,1000000",
                        help="bathtub sizes (273, 5000) and clean program sizes (others)")
    parser.add_argument("--one", nargs=2, metavar=("KIND", "SIZE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(one(args.one[0], int(args.one[1]))))
        return 0
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        kind = "bathtub" if size in (273, 5000) else "clean"
        runs = []
        for _ in range(args.runs if size < 1_000_000 else 1):  # 1M: one run (minutes)
            res = subprocess.run([sys.executable, __file__, "--one", kind, str(size)], capture_output=True,
                                 text=True, check=True)
            runs.append(json.loads(res.stdout.strip().splitlines()[-1]))
        med = {k: float(np.median([r[k] for r in runs])) for k in runs[0]}
        med["runs"] = len(runs)
        rows.append((kind, size, med))
        _print([rows[-1]])
    print()
    _print(rows)
    return 0


def _print(rows) -> None:
    head = (f"{'workload':<16}{'runs':>5}{'blocks':>9}{'poses':>10}{'hits':>6}{'load':>7}{'model':>7}{'grids':>7}"
            f"{'check':>8}{'report':>7}{'blocks/s':>10}{'exact parts':>12}{'exact':>8}{'ratio':>7}{'labels':>8}{'store MB':>9}"
            f"{'peak MB':>9}")
    print(head)
    for kind, size, m in rows:
        exact = m.get("exact")
        ratio = f"{exact / m['check']:.1f}x" if exact else "-"
        labels = f"{m['labels']:.2f}" if m.get("labels") else "-"
        print(f"{kind + ' ' + str(size):<16}{int(m['runs']):>5}{int(m['blocks']):>9}{int(m['poses']):>10}"
              f"{int(m['colliding']):>6}{m['load']:>7.2f}{m['head model']:>7.2f}{m['grids']:>7.2f}{m['check']:>8.2f}"
              f"{m['report']:>7.3f}{m['blocks'] / m['check']:>10.0f}{(format(m['exact parts'], '.2f') if exact else '-'):>12}{(f'{exact:.2f}' if exact else '-'):>8}"
              f"{ratio:>7}{labels:>8}{m['store_mb']:>9.1f}{m['peak_mb']:>9.0f}")


if __name__ == "__main__":
    raise SystemExit(main())
