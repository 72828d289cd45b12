"""The meshless model (`model.kind: meshless`, docs/method.md §19): [HZ]'s moving-least-squares
model with nodal integration on the mesh vertices.

neighbourhoods  k nearest nodes and support radii (cKDTree)
mls             kernel, moment matrices, gradient operator
forces          Green strain / StVK + volume term; energy, exact forces, stiffness
(assembly: fem/assembly.py, whose pattern takes stencils (n, k+1) as it takes tets (n, 4))
explicit        RK4 with sub-steps and its contact projection
model           MeshlessModel, the model the Simulator steps
"""
