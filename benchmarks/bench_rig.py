"""Benchmark: rig weight computation - sparse thin-shell solve vs a dense solve baseline.

On the ICT-FaceKit face region (9,409 vertices) with J joints at farthest-point vertices, times:

* mocaptk: ``thin_shell_weights`` (one sparse LU of the free-vertex block, scipy SuperLU) plus
  the region shaping and top-4 capping that ``build_rig`` adds (regions = geodesic Voronoi);
* dense baseline: the same ``W = -A_ff^-1 A_fm`` with ``numpy.linalg.solve`` on the dense block
  (what a naive implementation does); checked equal to 1e-8.

Wall and CPU seconds, best of ``--repeat``; the CPU ratio is the reliable one on a busy machine.

    python benchmarks/bench_rig.py [--joints 40,80] [--repeat 2]
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def best(fn, repeat: int) -> tuple[float, float, object]:
    wall, cpu, out = np.inf, np.inf, None
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn()
        wall = min(wall, time.perf_counter() - w0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu, out


def main() -> None:
    from mocaptk.acquisition.face_model import load_face_model
    from mocaptk.retarget.influence import edge_graph, main_influence_regions
    from mocaptk.retarget.weights import (cap_weights, region_masks, shape_by_regions,
                                          thin_shell_weights)
    from mocaptk.thin_shell import thin_shell_operator

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--joints", default="40,80")
    parser.add_argument("--repeat", type=int, default=2)
    args = parser.parse_args()
    model = load_face_model()
    vertices = model.neutral[:model.face_vertex_count]
    faces = model.face_triangles
    graph = edge_graph(vertices, faces)
    print(f"ICT face: {len(vertices)} vertices, {len(faces)} triangles")
    print(f"{'joints':>6} {'mocaptk wall/cpu s':>20} {'dense wall/cpu s':>18} {'cpu ratio':>10}")
    for count in (int(j) for j in args.joints.split(",")):
        joints = [int(np.argmax(vertices[:, 2]))]
        dist = np.linalg.norm(vertices - vertices[joints[0]], axis=1)
        while len(joints) < count:
            joints.append(int(np.argmax(dist)))
            dist = np.minimum(dist, np.linalg.norm(vertices - vertices[joints[-1]], axis=1))
        joints = np.array(joints)

        def ours():
            w = thin_shell_weights(vertices, faces, joints, graph=graph)
            regions = main_influence_regions(graph, [np.array([j]) for j in joints])
            shaped = shape_by_regions(w, region_masks(graph, regions, len(joints), falloff_mm=25))
            cap_weights(shaped, max_influences=4)
            return w

        def dense():
            op = thin_shell_operator(vertices, faces).toarray()
            free = np.setdiff1d(np.arange(len(vertices)), joints)
            w = np.zeros((len(vertices), len(joints)))
            w[joints, np.arange(len(joints))] = 1.0
            w[free] = -np.linalg.solve(op[np.ix_(free, free)], op[np.ix_(free, joints)])
            return w

        w1, c1, a = best(ours, args.repeat)
        w2, c2, b = best(dense, args.repeat)
        assert np.abs(np.asarray(a) - np.asarray(b)).max() < 1e-8
        print(f"{count:>6} {w1:>9.2f} / {c1:<8.2f} {w2:>8.2f} / {c2:<7.2f} {c2 / c1:>9.1f}x")


if __name__ == "__main__":
    main()
