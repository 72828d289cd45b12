"""Full-space FEM force model: the small interface integrators see.

    energy(x)            -> E                       elastic energy
    forces(x)            -> (E, f_int (n_verts, 3))  f_int = dE/dx
    tangent(x, project)  -> (E, f_int, K data (nnz,)) K = d f_int / dx on the free DOFs

plus the mass matrix on the same sparsity pattern. Pinned vertices are removed from
the unknowns by the pattern (their rows and columns never enter K or M).
"""
import time
from functools import cached_property

import numpy as np

from .assembly import assemble_matrix, assemble_vector, stiffness_pattern
from .elements import ElementBuffers, element_forces, tet_geometry
from .mass import consistent_mass_elements, lumped_mass


class FreeDofs:
    """Free-DOF bookkeeping of a force model on a fem.assembly.StiffnessPattern (self.pattern,
    self.n_verts): pinned DOFs are dropped from vectors and restored as `fill`."""

    @property
    def n_free(self):
        return self.pattern.n_free

    def free(self, a):
        """Restrict a per-vertex array (n_verts, 3) to the free DOF vector (n_free,)."""
        return a.reshape(-1)[self.pattern.free_dof >= 0]

    def expand(self, a_free, fill=0.0):
        """Inverse of free(): (n_free,) -> (n_verts, 3) with pinned DOFs set to fill."""
        out = np.full(3 * self.n_verts, fill, dtype=np.float64)
        out[self.pattern.free_dof >= 0] = a_free
        return out.reshape(self.n_verts, 3)


class FEMForceModel(FreeDofs):
    """Elasticity of a tet mesh with one material.

    X: (n_verts, 3) rest positions; tets: (n_tets, 4) positively oriented;
    material: a mdss_ros.fem.materials material; pinned: vertex indices held fixed;
    mass: "lumped" or "consistent".
    """

    def __init__(self, X, tets, material, pinned=(), mass="lumped"):
        self.X = np.ascontiguousarray(X, dtype=np.float64)
        self.tets = np.ascontiguousarray(tets, dtype=np.int64)
        self.n_verts = len(self.X)
        self.material = material
        self.pinned = np.unique(np.asarray(pinned, dtype=np.int64))
        self.geom = tet_geometry(self.X, self.tets)
        self.vertex_mass = lumped_mass(self.tets, self.geom.volume, material.density, self.n_verts)
        if mass not in ("lumped", "consistent"):
            raise ValueError(f"mass must be 'lumped' or 'consistent', got {mass!r}")
        self.mass_kind = mass
        self.timings = {}
        self._buffers = None

    # The pattern and the mass matrix on it are made on first use. A reduced model's
    # subspace domain has a force model of its own, which needs the pattern only for the
    # exact tangent (training, or a domain without cubature samples): on a cached build of
    # armadillo_class the eleven patterns were 8-19 s of the start (np.union1d over every
    # element's 144 entries), for nothing the step reads.
    @cached_property
    def pattern(self):
        return stiffness_pattern(self.tets, self.n_verts, self.pinned)

    @cached_property
    def M_data(self):
        if self.mass_kind == "consistent":
            return assemble_matrix(self.pattern, consistent_mass_elements(self.geom.volume, self.material.density))
        M_data = np.zeros(self.pattern.nnz)
        M_data[self.pattern.diagonal] = np.repeat(self.vertex_mass, 3)[self.pattern.free_dof >= 0]
        return M_data

    @cached_property
    def M(self):
        return self.pattern.matrix(self.M_data)

    def _buf(self):
        # Results are consumed (assembled or summed) before the next evaluation, so one
        # set of buffers per model is safe and spares large allocations every step.
        if self._buffers is None:
            self._buffers = ElementBuffers(len(self.tets), want_hessian=False)
        return self._buffers

    def energy(self, x):
        e, _, _ = element_forces(x, self.tets, self.geom, self.material, want_hessian=False, out=self._buf())
        return float(e.sum())

    def forces(self, x):
        e, fe, _ = element_forces(x, self.tets, self.geom, self.material, want_hessian=False, out=self._buf())
        return float(e.sum()), assemble_vector(self.tets, fe, self.n_verts)

    def tangent(self, x, project=False, out=None):
        t0 = time.perf_counter()
        e, fe, Ke = element_forces(x, self.tets, self.geom, self.material, want_hessian=True, project=project,
                                   out=self._buf())
        t1 = time.perf_counter()
        f = assemble_vector(self.tets, fe, self.n_verts)
        K = assemble_matrix(self.pattern, Ke, out)
        t2 = time.perf_counter()
        self.timings = {"element_ms": 1e3 * (t1 - t0), "scatter_ms": 1e3 * (t2 - t1)}
        return float(e.sum()), f, K
