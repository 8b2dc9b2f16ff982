"""Closest points on a surface (``aniformer.surface.closest_points``), best of 5, both ways between the 18k-vertex
and the 369-vertex targets of ``bench/animate_bench.py --inputs DIR`` (the queries of a registration's
correspondence and of the preview). Run from a checkout, with ``PYTHONPATH`` at it to time another:

    python bench/closest_points_bench.py /tmp/bi
"""

import argparse
import time

import numpy as np
import trimesh

from aniformer.surface import closest_points


def best_of(runs: int, query) -> float:
    """The shortest wall time of ``runs`` calls of ``query()``."""
    times = []
    for _ in range(runs):
        began = time.perf_counter()
        query()
        times.append(time.perf_counter() - began)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("inputs", help="bench/animate_bench.py's --inputs folder (target_18k.obj, target_369.obj)")
    inputs = parser.parse_args().inputs
    big, small = (trimesh.load(f"{inputs}/target_{size}.obj", process=False) for size in ("18k", "369"))
    vertices, faces = np.asarray(big.vertices), np.asarray(big.faces)
    small_faces = np.asarray(small.faces)
    # the small body scaled and moved onto the big one, as a fitted template lies on its character
    small_vertices = np.asarray(small.vertices)
    small_vertices = ((small_vertices - small_vertices.mean(0)) / np.ptp(small_vertices, 0).max()
                      * np.ptp(vertices, 0).max() + vertices.mean(0))
    onto_small = best_of(5, lambda: closest_points(vertices, small_vertices, small_faces))
    onto_big = best_of(5, lambda: closest_points(small_vertices, vertices, faces))
    print(f"{len(vertices):,} points onto {len(small_vertices):,} vertices: {onto_small:.3f} s; "
          f"{len(small_vertices):,} points onto {len(vertices):,} vertices: {onto_big:.3f} s")


if __name__ == "__main__":
    main()
