"""Views per second on a dask LocalCluster of 1 and of 2 workers, in one run:

    python -m nerfgauge.generate.bench_dask [--views 60] [--res 96] [--spp 64] [--workers 1,2]

Each worker renders with one Dr.Jit thread, so the ratio is what a second worker (with its
own core) adds, as on a cluster whose workers each own their cores. The time is the whole
`generate --scheduler`: connecting, loading the scene on each worker, rendering, writing.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from nerfgauge.generate.distributed import dask_client, local_cluster, set_render_threads, wait_for_workers
from nerfgauge.generate.pipeline import GenerateConfig, generate


def views_per_second(config: GenerateConfig, workers: int, folder: Path) -> float:
    """generate `config` on a fresh LocalCluster of `workers` single-threaded workers."""
    with local_cluster(workers, threads_per_worker=1) as cluster:
        with dask_client(cluster.scheduler_address) as client:
            wait_for_workers(client, workers)
            client.run(set_render_threads, 1)
            start = time.perf_counter()
            result = generate(config, folder, scheduler=cluster.scheduler_address, progress=False)
            seconds = time.perf_counter() - start
    return result["views_rendered"] / seconds


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=60)
    parser.add_argument("--res", type=int, default=96)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--workers", default="1,2")
    args = parser.parse_args(argv)
    config = GenerateConfig(views=args.views, val_views=0, test_views=0, width=args.res, height=args.res, spp=args.spp)
    rates = {}
    with tempfile.TemporaryDirectory() as scratch:
        for count in (int(n) for n in args.workers.split(",")):
            rates[count] = views_per_second(config, count, Path(scratch) / f"w{count}")
            print(f"{count} worker(s): {rates[count]:.2f} views/s", flush=True)
    first = min(rates)
    for count, rate in rates.items():
        if count != first:
            print(f"{count} workers vs {first}: {rate / rates[first]:.2f}x views per second")


if __name__ == "__main__":
    main()
