#!/usr/bin/env python3
"""Builds a planned tiled map on a Dask cluster: one task per grid square.

    visnav map plan --ortho A.tif [--ortho B.tif ...] (--dem D.tif | --ground-height M) \\
        --tile-m 2000 --out MAP
    python3 scripts/map_build_dask.py MAP/plan.json [--scheduler tcp://HOST:8786] [--workers 2]

Every task runs `visnav map build-tile PLAN K` in a process of its own (the squares are
independent: docs/maps.md), then `visnav map gather` writes MAP/index.json. The result is the
same bytes as `visnav map build ... --tile-m 2000 --out MAP` on one machine: both run the same
code, and a tile records no build time.

Without --scheduler a LocalCluster of --workers processes runs here. With one, the workers must
see the plan's folder and every source file at the same absolute paths (a shared file system) and
have the visnav binary (--visnav, default `visnav` on the PATH). Squares an earlier run finished
are kept (visnav checks each tile's checksum), so a failed or killed run is resumed by running the
same command again.

Each square's build uses --threads-per-tile threads (RAYON_NUM_THREADS; default 1, one square per
core: give a worker as many threads as cores). Prints one line per square and a summary with the
throughput per core; exit 1 when a square failed (its visnav error is printed).
"""

import argparse
import json
import os
import subprocess
import sys
import time


def build_square(visnav, plan, k, threads):
    """Runs one square's job; returns (k, exit code, stdout, stderr tail, seconds)."""
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    t0 = time.monotonic()
    p = subprocess.run(
        [visnav, "map", "build-tile", plan, str(k)],
        capture_output=True,
        text=True,
        env=env,
        check=False,
    )
    return k, p.returncode, p.stdout.strip(), p.stderr.strip()[-4000:], time.monotonic() - t0


def squares_of(plan):
    """The plan's square count (its file is visnav's; only the list's length is read here)."""
    with open(plan, encoding="utf-8") as f:
        squares = json.load(f).get("squares")
    if not isinstance(squares, list):
        raise SystemExit(f"map_build_dask: {plan}: not a visnav tiled map plan (no squares)")
    return len(squares)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("plan", help="plan.json written by `visnav map plan`")
    ap.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://HOST:PORT)")
    ap.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes")
    ap.add_argument("--threads-per-tile", type=int, default=1, help="threads per square's build")
    ap.add_argument("--visnav", default="visnav", help="the visnav binary on the workers")
    args = ap.parse_args()
    if args.workers < 1 or args.threads_per_tile < 1:
        raise SystemExit("map_build_dask: --workers and --threads-per-tile must be at least 1")
    plan = os.path.abspath(args.plan)
    n = squares_of(plan)

    from dask.distributed import Client, LocalCluster, as_completed

    cluster = None
    if args.scheduler:
        client = Client(args.scheduler)
    else:
        cluster = LocalCluster(
            n_workers=args.workers,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
        )
        client = Client(cluster)
    cores = sum(client.nthreads().values())
    print(f"map_build_dask: {n} squares on {len(client.nthreads())} workers ({cores} slots)", flush=True)
    t0 = time.monotonic()
    futures = client.map(
        build_square,
        [args.visnav] * n,
        [plan] * n,
        range(n),
        [args.threads_per_tile] * n,
        pure=False,
    )
    failed, task_s = [], 0.0
    for _, (k, rc, out, err, secs) in as_completed(futures, with_results=True):
        task_s += secs
        if rc == 0:
            print(f"  {out}", flush=True)
        else:
            failed.append(k)
            print(f"  square {k} failed (exit {rc}): {err}", file=sys.stderr, flush=True)
    wall_s = time.monotonic() - t0
    client.close()
    if cluster is not None:
        cluster.close()
    if failed:
        print(f"map_build_dask: {len(failed)} of {n} squares failed: {sorted(failed)}; "
              "run the same command again to build them", file=sys.stderr)
        return 1
    g = subprocess.run([args.visnav, "map", "gather", plan], capture_output=True, text=True, check=False)
    if g.returncode != 0:
        print(f"map_build_dask: gather failed: {g.stderr.strip()[-4000:]}", file=sys.stderr)
        return 1
    print(g.stdout.strip())
    slots = max(1, cores) * args.threads_per_tile
    print(f"map_build_dask: {n} squares in {wall_s:.1f} s wall, {task_s:.1f} s in tasks; "
          f"{n / wall_s * 60.0 / slots:.2f} squares per minute per core ({slots} cores)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
