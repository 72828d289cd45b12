"""Compile and cache the numba kernels once, so a user's first scene does not pay for it.

numba compiles a kernel on its first call and, with ``cache=True``, writes the machine code
to $NUMBA_CACHE_DIR (the launch scripts point it into the venv). On a fresh install the
first scene paid ~20 s of compilation on a quiet 2-core machine and several times that
under load, in the middle of its precompute, where it looked like a hang. The bootstrap
runs this module once after installing, with a progress line, so the cost is paid where
the user expects to wait and is never paid again.

It steps three tiny models through the code paths a scene uses: a full-space model, a
reduced multi-domain model with cubature and a meshless model, each pressed by a rough
sphere collider, with the stability guard on (and a reduced one without the collider,
and one resting on a rough floor), then queries a mesh collider's grid. Nothing is cached but the kernels (the precompute cache is off).

    python -m mdss_ros.warmup          # prints one line per model and the time taken
"""
import sys
import time


def _scene_overrides(kind):
    """A 0.4 m cantilever at cell 0.05 (a few hundred tets) pressed by a sphere."""
    over = {
        "body.mesh.cell": 0.05,
        "body.mesh.size": [0.4, 0.1, 0.1],
        "handles.tip.box": [[0.399, -1, -1], [0.401, 1, 1]],
        # 0.5 mm clear, rough: the frictional contact's kernels compile too.
        "colliders": {"ball": {"shape": "sphere", "radius": 0.05, "position": [0.3, 0.05, 0.1505], "friction": 0.5}},
        "model.kind": kind,
    }
    if kind == "reduced":
        over.update({"model.domains": {"count": 2}, "model.modes": 6,
                     "model.cubature": {"samples": 12, "interface": "uniform", "interface_samples": 8}})
    return over


def warm(kinds=("full", "reduced", "meshless"), say=print):
    """Build and step each kind of model once; returns the seconds each took."""
    from . import threads
    from .precompute import PrecomputeCache
    from .simulator import Simulator
    times = {}
    for kind in kinds:
        t0 = time.perf_counter()
        sim = Simulator("cantilever", overrides=_scene_overrides(kind), cache=PrecomputeCache(enabled=False))
        sim.set_wrench("tip", force=(0.0, 0.0, -5.0))
        # Kernels run serially on small inputs and threaded on large ones (threads.pick):
        # step once with each, so both variants are compiled here.
        saved = threads.SERIAL_BELOW
        try:
            for serial_below in (saved, 0):
                threads.SERIAL_BELOW = serial_below
                sim.step(2)
                sim.surface_positions()
        finally:
            threads.SERIAL_BELOW = saved
        sim.collider_wrench("ball")
        if kind == "reduced":
            # A step without contact takes the compiled linear step (reduced/linear_step.py),
            # which alone compiles for about 9 s.
            alone = Simulator("cantilever", overrides=dict(_scene_overrides(kind), colliders={}),
                             cache=PrecomputeCache(enabled=False))
            alone.step()
            # A block resting on a rough floor: vertex contacts with friction take the
            # compiled rows and Coulomb solve (reduced/frictional_kernel.py), from the
            # second step in contact (a warm start).
            from .verify.friction_study import REDUCED, incline
            resting = Simulator(incline(20.0, REDUCED), cache=PrecomputeCache(enabled=False))
            resting.step(3)
        times[kind] = time.perf_counter() - t0
        say(f"  {kind} model kernels ready ({times[kind]:.1f} s)")
    # A mesh collider's grid query (contact/mesh_sdf.py), with and without normals: no
    # scene above has a mesh collider, and the grid needs no file to be queried.
    import numpy as np

    from .contact.mesh_sdf import MeshSDF
    grid = MeshSDF(np.zeros((3, 3, 3)), np.zeros(3), 1.0)      # np.gradient needs 3 nodes an axis
    grid.evaluate(np.zeros((1, 3)))
    grid.distance(np.zeros((1, 3)))
    return times


def main(argv=None):
    t0 = time.perf_counter()
    warm()
    print(f"  numba kernels compiled and cached in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
