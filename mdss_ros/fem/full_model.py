"""Full-space FEM model (`model.kind: full`): every vertex is an unknown.

The ground truth every reduced result is measured against.
"""
import numpy as np

from ..loads import VertexLoads
from ..rotations import quat_from_matrix
from ..state_measure import Measure, inverted_tets
from .backward_euler import BackwardEuler, NewtonSettings
from .force_model import FEMForceModel


class VertexState:
    """The part of a model whose state is every vertex's position and velocity x, v
    (n_verts, 3), with pinned vertices at rest: the full-space FEM and the meshless model.
    Needs body, vertex_mass, force_model (energy(x), n_free) and integrator (dt, step(x, v,
    f_ext, contact) -> (x, v), stats, contact: BackwardEuler or meshless.explicit.RK4)."""

    # Unknowns that are not the mesh's vertices (the meshless lattice's nodes) move them
    # through an embedding (meshless/embedding.py); None: the vertices are the unknowns.
    embedding = None

    @property
    def state_mass(self):
        """Masses (n,) of the unknowns x: the vertices' lumped masses here."""
        return self.vertex_mass

    def reset(self):
        self.x = self.body.vertices.copy()
        self.v = np.zeros_like(self.x)
        self.contact = None
        self._set_projected_run(0)

    def _set_projected_run(self, n):
        """The integrator's run of projected steps (backward_euler.PROBE_EVERY), if it has one."""
        if hasattr(self.integrator, "projected_run"):
            self.integrator.projected_run = int(n)

    @property
    def dt(self):
        return self.integrator.dt

    def set_dt(self, dt):
        """Change the step (collider sub-steps); the system is re-assembled every step anyway."""
        self.integrator.dt = float(dt)

    @property
    def n_dofs(self):
        return self.force_model.n_free

    # No moving frames, hence no fictitious forces (StepOptions.fictitious is ignored).
    fictitious = None

    @property
    def newton_iterations(self):
        """Newton iterations per step as configured (1 for an explicit integrator)."""
        return getattr(getattr(self.integrator, "settings", None), "max_iterations", 1)

    def step(self, f_ext, gravity=None, contact=None, options=None):
        """Advance by dt under per-vertex loads f_ext (n_verts, 3) plus gravity (3,);
        contact: see BackwardEuler.step (colliders at their end-of-step poses);
        options: a StepOptions for this step only (dt, Newton iterations)."""
        if isinstance(f_ext, VertexLoads):
            f_ext = f_ext.dense()            # every vertex is an unknown here anyway
        f_ext = np.asarray(f_ext, dtype=np.float64)
        if self.embedding is not None:
            f_ext = self.embedding.spread(f_ext, len(self.x))      # the same virtual work on the nodes
        if gravity is not None:
            f_ext = f_ext + self.state_mass[:, None] * np.asarray(gravity)[None, :]
        integ = self.integrator
        settings = getattr(integ, "settings", None)
        saved = (integ.dt, getattr(settings, "max_iterations", None))
        if options is not None:
            if options.dt:
                integ.dt = float(options.dt)
            if options.newton_iterations and saved[1] is not None:
                settings.max_iterations = max(saved[1], int(options.newton_iterations))
        if contact:
            contact = dict(contact, previous=self.contact)   # the last step's slip (friction.effective_mu)
        try:
            self.x, self.v = integ.step(self.x, self.v, f_ext, contact)
        finally:
            integ.dt = saved[0]
            if saved[1] is not None:
                settings.max_iterations = saved[1]
        self.contact = integ.contact
        return integ.stats

    def vertex_positions(self):
        return self.x

    def vertex_velocities(self):
        return self.v

    def positions_of(self, ids):
        return self.x[ids]

    def get_state(self, share=False):
        """A snapshot of the dynamic state (copies): {"x", "v" (n_verts, 3), "contact"}.
        set_state(snapshot) restores it exactly (the stability guard rolls back with it).
        share (model_api.Model.get_state) changes nothing here: x and v are written in
        place (pinned rows, set_rigid_velocity), so they are always copied."""
        return {"x": self.x.copy(), "v": self.v.copy(), "contact": self.contact,
                "projected_run": getattr(self.integrator, "projected_run", 0)}

    def set_state(self, x, v=None):
        """Restore a get_state() snapshot (x a dict), or set positions and velocities x, v
        (n_verts, 3), in which case pinned vertices keep their rest state."""
        if isinstance(x, dict):
            self.x, self.v = x["x"].copy(), x["v"].copy()
            self.contact = x.get("contact")
            self._set_projected_run(x.get("projected_run", 0))
            return
        if v is None:
            raise ValueError("set_state(x, v): v is missing (or pass a get_state() snapshot)")
        self._set_projected_run(0)           # a new configuration: the exact tangent first
        pinned = self.body.pinned
        self.x = np.array(x, dtype=np.float64)
        self.v = np.array(v, dtype=np.float64)
        self.x[pinned] = self.body.vertices[pinned]
        self.v[pinned] = 0.0

    def set_rigid_velocity(self, linear, angular, center=None):
        """Give the body the rigid velocity v + w x (x - center) (default: centre of mass)."""
        m = self.vertex_mass
        if center is None:
            center = (m[:, None] * self.x).sum(0) / m.sum()
        self.v = np.asarray(linear, float) + np.cross(np.asarray(angular, float), self.x - center)
        self.v[self.body.pinned] = 0.0

    def elastic_energy(self):
        return self.force_model.energy(self.x)

    def energies(self, gravity):
        """(kinetic, elastic, gravity potential) of the current state (J): the mesh
        vertices' -m g . x for gravity (3,)."""
        x = self.vertex_positions()
        return self.kinetic_energy(), self.elastic_energy(), -float((self.vertex_mass * (x @ gravity)).sum())

    def domain_poses(self):
        """One domain: the body's mass centre and best-fit rotation (polar decomposition)."""
        return best_fit_pose(self.body.vertices, self.x, self.vertex_mass)[None, :]

    # --- the rest of model_api.Model: one domain, the vertices are the state -------------
    can_untangle = False        # positions are the unknowns: nothing to shrink them towards

    @property
    def vertex_domain(self):
        return np.zeros(len(self.body.vertices), dtype=np.int64)

    def domain_names(self):
        return ["body"]

    def watch(self, ids):
        """positions_of is a gather: nothing to prepare."""

    def explain(self):
        return [f"{self.kind} model: every vertex an unknown, {self.n_dofs} DOFs ({self.body.pinned.size} "
                f"pinned vertices removed), no domains or modes"]

    def guard_measure(self, gravity, check_inversion=True):
        """state_measure.Measure from the vertices: kinetic, elastic and gravity energy,
        inverted elements of the body. Never raises on NaN."""
        with np.errstate(all="ignore"):
            x = np.asarray(self.vertex_positions(), dtype=np.float64)
            v = np.asarray(self.vertex_velocities(), dtype=np.float64)
            tets = self.body.tets
            if not (np.isfinite(x).all() and np.isfinite(v).all()):
                return Measure(x, v, np.nan, np.nan, np.nan, len(tets), False)
            m = self.vertex_mass
            kinetic = 0.5 * float((m * (v * v).sum(1)).sum())
            try:
                elastic = float(self.elastic_energy())
            except (ArithmeticError, ValueError, RuntimeError, np.linalg.LinAlgError):
                elastic = np.nan
            grav = -float((m * (x @ gravity)).sum())
            inverted = inverted_tets(x, tets) if check_inversion else 0
        finite = bool(np.isfinite([kinetic, elastic, grav]).all())
        return Measure(x, v, kinetic, elastic, grav, inverted, finite)

    def mean_motion(self):
        """(total mass, mass-centre velocity (3,)); zero velocity when pins hold the body
        (then nothing conserves momentum and all motion is scaled)."""
        m = self.vertex_mass
        if self.body.pinned.size:
            return float(m.sum()), np.zeros(3)
        return float(m.sum()), (m[:, None] * self.vertex_velocities()).sum(0) / m.sum()

    def scale_relative_motion(self, s, V):
        """The guard's energy projection: v <- V + s (v - V), pinned vertices at rest."""
        v = V + s * (np.asarray(self.vertex_velocities()) - V)
        v[self.body.pinned] = 0.0
        self.v = v

    def untangle(self, tets, bisections=8):
        return None


class EmbeddedNodes:
    """A VertexState whose unknowns x, v (n_nodes, 3) are nodes, not the mesh's vertices:
    the vertices (output, loads, contacts, the guard's inverted tets) follow the nodes by
    self.embedding (meshless/embedding.py). Mixed in before the model class; needs
    node_rest (n_nodes, 3), node_pinned (p,) node ids, embedding, and the nodes' masses as
    force_model.vertex_mass. vertex_mass stays the mesh's lumped vertex masses (what the
    Simulator spreads a handle's wrench by)."""

    @property
    def state_mass(self):
        return self.force_model.vertex_mass

    def reset(self):
        self.x = self.node_rest.copy()
        self.v = np.zeros_like(self.x)
        self.contact = None
        self._set_projected_run(0)

    def vertex_positions(self):
        return self.embedding.apply(self.x)

    def vertex_velocities(self):
        return self.embedding.apply(self.v)

    def positions_of(self, ids):
        return self.embedding.apply(self.x, ids)

    def set_state(self, x, v=None):
        if not isinstance(x, dict):
            raise ValueError(f"set_state(x, v): the mesh vertices of this {self.kind} model follow its nodes and "
                             "cannot be set one by one; pass a get_state() snapshot")
        super().set_state(x)

    def set_rigid_velocity(self, linear, angular, center=None):
        m = self.state_mass
        if center is None:
            center = (m[:, None] * self.x).sum(0) / m.sum()
        self.v = np.asarray(linear, float) + np.cross(np.asarray(angular, float), self.x - center)
        self.v[self.node_pinned] = 0.0

    def domain_poses(self):
        return best_fit_pose(self.node_rest, self.x, self.state_mass)[None, :]

    def guard_measure(self, gravity, check_inversion=True):
        """As VertexState's, with the energies of the nodes (the inverted tets those of
        the mesh the nodes move)."""
        with np.errstate(all="ignore"):
            x, v = self.vertex_positions(), self.vertex_velocities()
            if not (np.isfinite(self.x).all() and np.isfinite(self.v).all()):
                return Measure(x, v, np.nan, np.nan, np.nan, len(self.body.tets), False)
            m = self.state_mass
            kinetic = self.kinetic_energy()
            try:
                elastic = float(self.elastic_energy())
            except (ArithmeticError, ValueError, RuntimeError, np.linalg.LinAlgError):
                elastic = np.nan
            grav = -float((m * (self.x @ gravity)).sum())
            inverted = inverted_tets(x, self.body.tets) if check_inversion else 0
        return Measure(x, v, kinetic, elastic, grav, inverted, bool(np.isfinite([kinetic, elastic, grav]).all()))

    def mean_motion(self):
        m = self.state_mass
        if self.node_pinned.size:
            return float(m.sum()), np.zeros(3)
        return float(m.sum()), (m[:, None] * self.v).sum(0) / m.sum()

    def scale_relative_motion(self, s, V):
        self.v = V + s * (self.v - V)
        self.v[self.node_pinned] = 0.0


class FullSpaceModel(VertexState):
    """State x, v (n_verts, 3). step(f_ext) advances by dt with backward Euler."""

    kind = "full"

    def __init__(self, body, dt, integrator, damping, mass="lumped", solver="auto"):
        self.body = body
        self.force_model = FEMForceModel(body.vertices, body.tets, body.material, body.pinned, mass=mass)
        settings = NewtonSettings(max_iterations=integrator["newton_iterations"],
                                  tolerance=integrator["tolerance"],
                                  line_search=integrator["line_search"],
                                  projection=integrator["projection"],
                                  projection_memory=integrator.get("projection_memory", True),
                                  alpha=damping["alpha"], beta=damping["beta"])
        self.integrator = BackwardEuler(self.force_model, dt, settings, solver)
        self.vertex_mass = self.force_model.vertex_mass
        self.reset()

    def kinetic_energy(self):
        return 0.5 * float((self.vertex_mass * (self.v * self.v).sum(1)).sum()) if self.force_model.mass_kind == "lumped" \
            else 0.5 * float(self.force_model.free(self.v) @ (self.force_model.M @ self.force_model.free(self.v)))



def best_fit_pose(X, x, mass):
    """(7,) x y z qx qy qz qw of the rigid motion best fitting X -> x (mass-weighted).

    X, x (n, 3), mass (n,). The centres are products with the normalised masses and the
    cross-covariance one product (the node asks a pose every step: on grasp_lift's 125
    vertices 101-119 us before, 79-111 us so, alternated in one process)."""
    w = mass / mass.sum()
    c0 = w @ X
    c = w @ x
    A = (x - c).T @ ((X - c0) * w[:, None])
    U, _, Vt = np.linalg.svd(A)
    R = U @ Vt
    if np.linalg.det(R) < 0:
        U[:, -1] *= -1
        R = U @ Vt
    return np.concatenate([c, quat_from_matrix(R)])
