"""Builds msg_scenes/octopus.vtu, the octopus scene's mesh: a head and eight arms, the union
of primitives tetrahedralised by the composite generator (manifold3d + fTetWild).

fTetWild's output differs from run to run, so the scene loads this stored file: the same
mesh on every run keeps the precompute cache valid. Re-run after editing PRIMITIVES:

    PYTHONPATH=. python msg_scenes/make_octopus_mesh.py [edge_length]
"""
import sys
from pathlib import Path

import numpy as np


def octopus_primitives(arm_length=0.34, arm_radius=0.03, tilt=0.35):
    """Head ellipsoid at the origin and eight capsule arms radiating from under it,
    tilted `tilt` rad below the horizontal; arm k points at azimuth k * 45 deg."""
    prims = [{"shape": "ellipsoid", "radii": [0.11, 0.11, 0.14], "position": [0.0, 0.0, 0.06]}]
    r0 = 0.07                                 # arm root: inside the head
    for k in range(8):
        th = k * np.pi / 4
        d = np.array([np.cos(th) * np.cos(tilt), np.sin(th) * np.cos(tilt), -np.sin(tilt)])
        c = (r0 + arm_length / 2) * d
        prims.append({"shape": "capsule", "radius": arm_radius, "height": arm_length,
                      "position": [round(float(v), 5) for v in c],
                      "rotation_rpy": [0.0, round(np.pi / 2 + tilt, 5), round(th, 5)]})
    return prims


def arm_direction(k, tilt=0.35):
    th = k * np.pi / 4
    return np.array([np.cos(th) * np.cos(tilt), np.sin(th) * np.cos(tilt), -np.sin(tilt)])


def main(edge_length=0.02):
    from mdss_ros.mesh import composite, save_mesh
    mesh = composite(octopus_primitives(), edge_length=edge_length)
    out = Path(__file__).resolve().parent / "octopus.vtu"
    save_mesh(out, mesh)
    print(f"{out}: {len(mesh.vertices)} vertices, {len(mesh.tets)} tets (edge_length {edge_length})")


if __name__ == "__main__":
    main(*(float(a) for a in sys.argv[1:]))
