"""Quadratic (10-node) tetrahedra: a full-space model that does not lock in bending
(`model.kind: full` with `model.element: quadratic`; docs/method.md §4.1).

Linear tets are too stiff in bending on the meshes a robot scene uses: the 1 m cantilever
scene's first frequency is 8 % above Euler-Bernoulli on its 1,025 vertices, and a model
that does not lock (the meshless one, §19.7) then reads as "wrong" against it. A quadratic
tet on the same mesh is the standard cure, and is what `mdss tradeoff --set
truth_element=quadratic` measures against.

Nodes: the mesh's vertices, then one at the middle of every edge. Per tet (nodes 0-3 its
corners, 4-9 the edges 01 02 03 12 13 23), barycentric L (4,), grad L_a constant:

    N_a  = L_a (2 L_a - 1),            grad N_a  = (4 L_a - 1) grad L_a
    N_ab = 4 L_a L_b,                  grad N_ab = 4 (L_b grad L_a + L_a grad L_b)

and F at each of 4 quadrature points (degree 2: exact for the linear-elastic stiffness)

    F_q = sum_{a in 10 nodes} x_a (grad N_a(q))^T,    weight V_tet / 4.

That is F = sum_a x_{s_qa} c_qa^T over a stencil of 10 nodes, the algebra of the meshless
model's nodal stencils: the energy, forces and stiffness are meshless.forces.MeshlessForces'
on these stencils with k_v = 0 and no stabilisation: for `stvk` St. Venant-Kirchhoff plus
the materials' compression barrier (§3.4) (the FEM's stvk also clamps singular values below
0.5, Irving et al.; the quadratic model has no such clamp, so it is for moderate strain:
a truth, not a default); for `corotated` and `neohookean` the FEM's own point law
(fem/materials.py, barrier included) at each quadrature point, evaluated in one batch.

Mass: HRZ lumping (Hinton, Rock, Zienkiewicz 1976) of the consistent mass, which for a
10-node tet gives rho V / 36 to each corner and 4 rho V / 27 to each edge node (row sums
would give the corners negative mass). The mesh's vertices are the corner nodes
(fem/full_model.EmbeddedNodes with an identity embedding); an edge node is pinned when
both its ends are.
"""
import numpy as np

from ..meshless.embedding import Embedding
from ..meshless.forces import MeshlessForces
from ..meshless.mls import GradientOperator
from ..mesh.tetmesh import signed_volumes
from .backward_euler import BackwardEuler, NewtonSettings
from .elements import tet_geometry
from .full_model import EmbeddedNodes, VertexState
from .mass import lumped_mass

EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_A, _B = 0.5854101966249685, 0.1381966011250105           # 4-point rule: permutations of (a, b, b, b)
QUAD_L = np.full((4, 4), _B) + np.eye(4) * (_A - _B)      # (q, 4) barycentric coordinates
CORNER_MASS, EDGE_MASS = 1.0 / 36.0, 4.0 / 27.0           # HRZ, of rho V_tet


def quadratic_mesh(vertices, tets):
    """(nodes (n_v + n_e, 3), elements (t, 10)): the vertices, then one node at the middle of
    every edge; element columns 0-3 the corners, 4-9 the edges 01 02 03 12 13 23."""
    V = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(tets, dtype=np.int64)
    e = np.sort(T[:, EDGES], axis=2).reshape(-1, 2)                # (6 t, 2)
    edges, inverse = np.unique(e, axis=0, return_inverse=True)
    nodes = np.concatenate([V, 0.5 * (V[edges[:, 0]] + V[edges[:, 1]])])
    elements = np.concatenate([T, len(V) + inverse.reshape(-1, 6)], axis=1)
    return nodes, elements, edges


def shape_gradients(nodes, elements):
    """(c (4 t, 10, 3), weights (4 t,)): grad N of the 10 nodes at each quadrature point and
    the point's volume weight (V_tet / 4), rows ordered tet-major."""
    T = np.asarray(elements, dtype=np.int64)
    geo = tet_geometry(nodes, T[:, :4])                             # grad L_a (t, 4, 3): the linear tet's
    gL, vol = geo.grads, geo.volume
    L = QUAD_L                                                      # (q, 4)
    c = np.empty((len(T), 4, 10, 3))
    c[:, :, :4] = (4.0 * L - 1.0)[None, :, :, None] * gL[:, None, :, :]
    a, b = EDGES[:, 0], EDGES[:, 1]
    c[:, :, 4:] = 4.0 * (L[None, :, b, None] * gL[:, None, a, :] + L[None, :, a, None] * gL[:, None, b, :])
    return c.reshape(-1, 10, 3), np.repeat(vol / 4.0, 4)


def hrz_masses(nodes, elements, density):
    """(n,) HRZ-lumped masses: rho V / 36 to each corner, 4 rho V / 27 to each edge node."""
    T = np.asarray(elements, dtype=np.int64)
    vol = np.abs(signed_volumes(nodes, T[:, :4]))
    m = np.zeros(len(nodes))
    np.add.at(m, T[:, :4].ravel(), np.repeat(CORNER_MASS * density * vol, 4))
    np.add.at(m, T[:, 4:].ravel(), np.repeat(EDGE_MASS * density * vol, 6))
    return m


class QuadraticFullModel(EmbeddedNodes, VertexState):
    """Full-space model on 10-node tets (module docstring): state x, v (n_nodes, 3), the
    mesh's vertices the first n_verts nodes."""

    kind = "full"

    def __init__(self, body, dt, integrator, damping, solver="auto"):
        material = body.material
        self.body = body
        nodes, self.elements, edges = quadratic_mesh(body.vertices, body.tets)
        pinned = np.zeros(len(nodes), dtype=bool)
        pinned[body.pinned] = True
        pinned[len(body.vertices):] = pinned[edges[:, 0]] & pinned[edges[:, 1]]
        self.node_rest, self.node_pinned = nodes, np.flatnonzero(pinned)
        c, w = shape_gradients(nodes, self.elements)
        stencil = np.repeat(self.elements, 4, axis=0)                # (4 t, 10): each point's element
        op = GradientOperator(stencil=stencil, c=np.ascontiguousarray(c), weights=np.ones((len(c), 9)),
                              cond=np.ones(len(c)), floored=0)
        masses = hrz_masses(nodes, self.elements, material.density)
        if material.name == "stvk":
            # The meshless StVK (no singular-value clamp, see the module docstring), compiled.
            self.force_model = MeshlessForces(nodes, op, w, masses, material.mu, material.lam, 0.0,
                                              self.node_pinned, None, material.barrier * material.mu,
                                              material.barrier_j)
        else:
            # The FEM's own point law (corotated, neo-Hookean with its barrier) at every
            # quadrature point: the same material as a linear-tet model of the scene.
            self.force_model = MeshlessForces(nodes, op, w, masses, material.mu, material.lam, 0.0,
                                              self.node_pinned, material=material)
        n_v = len(body.vertices)
        self.embedding = self.force_model.embedding = Embedding(np.arange(n_v)[:, None], np.ones((n_v, 1)))
        self.embedding.n_nodes = len(nodes)
        settings = NewtonSettings(max_iterations=integrator["newton_iterations"], tolerance=integrator["tolerance"],
                                  line_search=integrator["line_search"], projection=integrator["projection"],
                                  alpha=damping["alpha"], beta=damping["beta"])
        self.integrator = BackwardEuler(self.force_model, dt, settings, solver)
        self.vertex_mass = material.density * lumped_mass(body.tets, signed_volumes(body.vertices, body.tets),
                                                          1.0, n_v)
        self.reset()

    def kinetic_energy(self):
        return 0.5 * float((self.state_mass * (self.v * self.v).sum(1)).sum())

    def explain(self):
        law = ("StVK with the compression barrier" if self.body.material.name == "stvk" else
               f"the FEM's {self.body.material.name} law with its compression barrier")
        return [f"full model on quadratic (10-node) tets: {len(self.node_rest)} nodes ({len(self.body.vertices)} "
                f"vertices + {len(self.node_rest) - len(self.body.vertices)} edge nodes), {self.n_dofs} DOFs, "
                f"4 quadrature points a tet, HRZ-lumped mass, {law} (docs/method.md §4.1)"]
