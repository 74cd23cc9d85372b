"""Views per second on a dask LocalCluster of 1 and of 2 workers, in one run:

    nerfgauge bench dask [--views 60] [--res 96] [--spp 64] [--workers 1,2] [--out DIR]

Each worker renders with one Dr.Jit thread, so the ratio is what a second worker (with its
own core) adds, as on a cluster whose workers each own their cores. The time is the whole
`generate --scheduler`: connecting, loading the scene on each worker, rendering, writing.
"""

from __future__ import annotations

import time
from pathlib import Path

from nerfgauge.core import owned
from nerfgauge.core.files import write_json
from nerfgauge.core.folders import remove_owned

from nerfgauge.generate.distributed import dask_client, local_cluster, set_render_threads, wait_for_workers
from nerfgauge.generate.pipeline import GenerateConfig, generate
from nerfgauge.orchestrate.bench.common import claim_bench_folder


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


def bench_dask(out: Path, views: int, res: int, spp: int, workers: tuple, log=print) -> dict:
    """Views per second for each worker count (datasets in OUT/runs/, a bench folder), and
    each count's ratio to the first; writes OUT/dask.json and returns it."""
    config = GenerateConfig(views=views, val_views=0, test_views=0, width=res, height=res, spp=spp)
    rates = {}
    with claim_bench_folder(out, "dask"):
        runs = owned.make_folder(out / "runs")
        for count in workers:
            folder = runs / f"w{count}"
            if folder.exists():
                remove_owned(folder, "dataset")
            rates[count] = views_per_second(config, count, folder)
            log(f"{count} worker(s): {rates[count]:.2f} views/s")
        first = workers[0]
        document = {"views_per_second": {str(k): v for k, v in rates.items()},
                    "ratio_to_first": {str(k): v / rates[first] for k, v in rates.items()},
                    "command": f"nerfgauge bench dask --views {views} --res {res} --spp {spp} "
                               f"--workers {','.join(map(str, workers))}"}
        write_json(out / "dask.json", document)
    for count, rate in rates.items():
        if count != first:
            log(f"{count} workers vs {first}: {rate / rates[first]:.2f}x views per second")
    return document
