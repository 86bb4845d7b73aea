#!/usr/bin/env python3
"""The README's 30-frames-a-second table: every thesis world at 15 m, positioning at 30 frames a second, the survey
mapped at 2, seeded runs; the fused output's figures per world as Markdown, and each world's JSON.

    .venv/bin/python tools/fps30_table.py --runs 3 --out docs/fps30_table.md [--json-dir out/fps30]

Each row is `auxgps eval --world config/worlds/W.yaml --altitude 15 --runs 3 --fps 30 --mapping-fps 2`.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from auxgps.config import load_pipeline_config  # noqa: E402
from auxgps.evaluation.driver import run_job  # noqa: E402
from auxgps.evaluation.metrics import summarize  # noqa: E402
from auxgps.sim.flight import load_sim_config  # noqa: E402

WORLDS = [f"one_cube_{s}" for s in ("0.5m", "1m", "2m", "3m")] + [
    f"cubes{n}_{s}_{c}" for n in (2, 3, 4) for s in ("0.5m", "3m") for c in ("different", "same")]


def row(world: str, summary: dict) -> str:
    fu, gate = summary["fused"], summary["gate"]
    per_seed = ", ".join(f"{r['fused']['max_m']:.2f}" for r in summary["runs"])
    return (f"| {world} | {fu['rms_m']:.3f} | {fu['p95_m']:.3f} | {fu['max_m']:.3f} | {per_seed} | {gate['rejected']} | "
            f"{gate['accepted_over_0_5m']} | {fu['within_3sigma']:.3f} | {fu['nees_mean']:.2f} | {fu['longest_gap_s']:.1f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=1, help="seeds first-seed .. first-seed + runs - 1 (default 1)")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--mapping-fps", type=float, default=2.0)
    ap.add_argument("--altitude", type=float, default=15.0)
    ap.add_argument("--worlds", help="comma-separated subset (default: all 16)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--config")
    ap.add_argument("--sim-config")
    ap.add_argument("--out", default="docs/fps30_table.md")
    ap.add_argument("--json-dir", default="out/fps30")
    args = ap.parse_args(argv)
    pipeline, sim = load_pipeline_config(args.config), load_sim_config(args.sim_config)
    worlds = args.worlds.split(",") if args.worlds else WORLDS
    json_dir = Path(args.json_dir)
    json_dir.mkdir(parents=True, exist_ok=True)
    head = [
        "| world | fused RMS m | fused p95 m | fused max m | max per seed m | fixes gated | accepted > 0.5 m | within 3 sigma | NEES | longest gap s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    t0 = time.monotonic()
    # Every (world, seed) run in one pool, so that no worker idles at a world's last run; a world's row is written
    # as soon as its runs are in, in the table's order.
    jobs = [(str(REPO / "config" / "worlds" / f"{w}.yaml"), args.altitude, args.fps, 1 + k, pipeline, sim, args.mapping_fps)
            for w in worlds for k in range(args.first_seed - 1, args.first_seed - 1 + args.runs)]
    records: dict[str, list] = {w: [] for w in worlds}
    rows: dict[str, str] = {}
    with ProcessPoolExecutor(args.workers) as pool:
        futures = {pool.submit(run_job, job): Path(job[0]).stem for job in jobs}
        for fut in as_completed(futures):
            w = futures[fut]
            records[w].append(fut.result())
            if len(records[w]) < args.runs:
                continue
            recs = sorted(records[w], key=lambda r: r.seed)
            summary = summarize(recs)
            summary["scenario"] = {"world": w, "altitude_m": args.altitude, "fps": args.fps, "mapping_fps": args.mapping_fps,
                                   "runs": args.runs, "seeds": [r.seed for r in recs]}
            (json_dir / f"{w}.json").write_text(json.dumps(summary, indent=2, default=str))
            rows[w] = row(w, summary)
            print(rows[w], flush=True)
            done = "" if len(rows) == len(worlds) else f" ({len(rows)} of {len(worlds)} worlds so far)"
            header = (f"# Fused output at {args.fps:g} frames a second\n\n`.venv/bin/python tools/fps30_table.py --runs {args.runs}` "
                      f"(each row: `auxgps eval --world config/worlds/W.yaml --altitude {args.altitude:g} --runs {args.runs} --fps {args.fps:g} "
                      f"--mapping-fps {args.mapping_fps:g}`), {time.monotonic() - t0:.0f} s on this machine{done}. Seeds {args.first_seed} to {args.first_seed + args.runs - 1}; "
                      "figures over the GPS-denied part of the positioning flight, each output scored at the time it describes.\n\n")
            table = head + [rows[x] for x in worlds if x in rows]
            Path(args.out).write_text(header + "\n".join(table) + "\n")  # after every world: a cut run keeps what it did
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
