"""The interface every simulation model offers: full-space FEM (fem/full_model.py), the
multi-domain subspace model (reduced/reduced_model.py) and the meshless model
(meshless/model.py).

The Simulator, the stability guard, the node and the recorders talk to a model only
through these names, so none of them probes a model with hasattr. test_model_api.py
checks that every kind implements all of them.

Shapes: n_verts body vertices, d domains (1 for a model without domains).
"""
from typing import Protocol, runtime_checkable


@runtime_checkable
class Model(Protocol):
    kind: str                  # "full", "reduced" or "meshless"
    body: object               # the Body it simulates (vertices, tets, surface, pinned, material)
    vertex_mass: object        # (n_verts,) lumped masses
    vertex_domain: object      # (n_verts,) domain index of each vertex
    contact: object            # the last step's active contacts (dict) or None
    newton_iterations: int     # Newton iterations per step as configured
    fictitious: object         # "explicit" / "implicit" fictitious forces, None: no moving frames
    can_untangle: bool         # untangle() can undo inverted elements (the guard's last resort)

    @property
    def dt(self): ...

    @property
    def n_dofs(self): ...

    def step(self, f_ext, gravity=None, contact=None, options=None):
        """Advance one step (StepOptions: dt, iterations, fictitious); returns stats (dict)."""

    def reset(self): ...

    def get_state(self, share=False):
        """A snapshot (copies) that set_state restores exactly. share=True: arrays the model
        only ever replaces may be shared instead of copied (a rollback around steps, the
        stability guard's); set_state copies them back."""

    def set_state(self, state): ...

    def set_dt(self, dt): ...

    def vertex_positions(self):
        """(n_verts, 3)."""

    def vertex_velocities(self):
        """(n_verts, 3)."""

    def positions_of(self, ids):
        """(len(ids), 3) world positions of global vertex ids."""

    def watch(self, ids):
        """Hint: positions_of(ids) will be asked for every frame (the surface)."""

    def elastic_energy(self): ...

    def kinetic_energy(self): ...

    def energies(self, gravity):
        """(kinetic, elastic, gravity potential -sum m g . x) of the current state, J;
        gravity (3,). Simulator.energy reports them."""

    def guard_measure(self, gravity, check_inversion=True):
        """state_measure.Measure of the current state (never raises on NaN)."""

    def mean_motion(self):
        """(total mass, mass-centre velocity (3,)); zero velocity for a pinned body."""

    def scale_relative_motion(self, s, V):
        """v <- V + s (v - V): the guard's energy projection."""

    def untangle(self, tets, bisections=8):
        """Shrink the deformation until no element of tets is inverted; the factor or None."""

    def domain_names(self):
        """(d,) names of the domains, in domain_poses order."""

    def domain_poses(self):
        """(d, 7) x y z qx qy qz qw of each domain's frame."""

    def explain(self):
        """What the model took and why (list of str)."""
