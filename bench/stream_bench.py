"""On-the-fly pair generation (data.source: stream): throughput per CPU and its scaling with Ray Data.

    python bench/stream_bench.py [--topology notoes_collapse3pc] [--pairs 3072] [--out bench/results/stream.json]

1. One process, no Ray: ``StreamPairs.batch`` on the training split, 64 pairs a call (the Ray Data
   block size), after a warm-up epoch (Anny build, library clip cache).
2. Ray Data: ``pipeline.data.pair_dataset`` over the stream read to the end on the driver, on a local
   ``ray.cluster_utils.Cluster`` of one node with 1 CPU, one node with 2 CPUs, and two nodes of 1 CPU
   each. Every setting reads three epochs of pairs: the first includes starting worker processes,
   and every process fills its own library-clip cache over the first epochs; the third is closest
   to what a long training sees.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from aniformer.synth.stream import StreamPairs


def bench_process(stream: StreamPairs, pairs: int) -> float:
    for lo in range(0, pairs, 64):  # an epoch to fill the library-clip cache, then the measured one
        stream.batch("train", 99, np.arange(lo, lo + 64))
    start = time.perf_counter()
    for lo in range(0, pairs, 64):
        stream.batch("train", 0, np.arange(lo, lo + 64))
    return pairs / (time.perf_counter() - start)


def bench_cluster(stream: StreamPairs, pairs: int, nodes: list[int]) -> dict:
    import ray
    from ray.cluster_utils import Cluster

    from pipeline.data import pair_dataset, quiet_ray_data

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": nodes[0], "include_dashboard": False})
    for cpus in nodes[1:]:
        cluster.add_node(num_cpus=cpus)
    cluster.wait_for_nodes()
    ray.init(address=cluster.address)
    quiet_ray_data()
    try:
        rates = []
        for epoch in range(3):
            ds = pair_dataset(stream, "train", first_epoch=epoch, pairs=pairs)
            start = time.perf_counter()
            count = sum(len(b["index"]) for b in ds.iter_batches(batch_size=64, batch_format="numpy"))
            assert count == pairs
            rates.append(pairs / (time.perf_counter() - start))
    finally:
        ray.shutdown()
        cluster.shutdown()
    return {"nodes": nodes, "pairs_per_s_by_epoch": [round(r, 1) for r in rates]}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--topology", default="notoes_collapse3pc")
    p.add_argument("--pairs", type=int, default=3072)
    p.add_argument("--out", default="bench/results/stream.json")
    args = p.parse_args()
    stream = StreamPairs(args.topology, window=3)
    result = {"topology": args.topology, "vertices": stream.num_vertices, "pairs": args.pairs,
              "one_process_pairs_per_s": round(bench_process(stream, args.pairs), 1), "ray_data": []}
    print(f"one process: {result['one_process_pairs_per_s']} pairs/s", flush=True)
    for nodes in ([1], [2], [1, 1]):
        row = bench_cluster(stream, args.pairs, nodes)
        result["ray_data"].append(row)
        print(f"Ray Data on nodes with {nodes} CPUs: {row['pairs_per_s_by_epoch']} pairs/s in epochs 1-3", flush=True)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
