"""Phi + adjoint gradient: hand-written adjoint against dolfinx-adjoint's taped one (serial).

    make bench-adjoint      (sets up .venv-bench, then runs this)

Same problem for both: 3D linear elasticity, P2 on a 13x9x9 tetrahedral box (29,241 DOFs),
bottom clamped, unknown traction g (vector P1 Function on the whole mesh) acting through
ds(top), misfit Phi = 1/2 int_top |u - u_target|^2 against the response to a known traction.
Both solve with MUMPS LU.

- hand: K (symmetric, bc rows and columns eliminated) is assembled and factorized once;
  Phi = one back-solve with b = B g, where B is the traction mass term int_top g.v;
  the gradient is one more back-solve K lam = M (u - u_target) with the same factors
  (K = K^T), then dPhi/dg = B^T lam (dual/l2 components, like pyadjoint's derivative).
- taped: dolfinx_adjoint.LinearProblem + assemble_scalar record a pyadjoint tape; the
  ReducedFunctional replays it. Its forward and adjoint solvers each re-assemble their
  matrix and re-factorize on every call (dolfinx_adjoint 0.4.0 does not reuse factors).

dolfinx-adjoint is for this benchmark only, in a venv of its own (.venv-bench) that sees
the project's packages; `make bench-adjoint` builds it (see the Makefile for why --no-deps).

After a material change the toolkit does not assemble K again: K = mu A + lam B from
matrices assembled once (model/stiffness.py), then a new factorization, or -- for a
change within NEARBY_RATIO -- CG preconditioned by the factors it already holds
(model/solvers.py NearbySolver). The box is not a scene, so those two steps are written
out here on its matrices; "re-assembling and re-factorizing" is the plain path.

Measured on this machine (2026-12-05; 2 cores, serial; dolfinx 0.11.0.post0,
dolfinx-adjoint 0.4.0, pyadjoint-ad 2026.10.0; two runs, the second's seconds). Gradients
agree to 7.7e-15 (relative), and both match a central finite difference along a random
direction to 10 digits; at the new materials (E 10 -> 12, nu 0.3 -> 0.32) the gradient on
held factors (6 CG iterations) equals the re-factorized one to 2.9e-11.

| quantity | seconds | ratio to Phi (hand) |
|---|---|---|
| Phi (hand, cached factorization) | 0.0263 | 1.00 |
| Phi + gradient (hand) | 0.0579 | 2.20 |
| Phi + gradient (hand, re-assembling and re-factorizing K first) | 0.9045 | 34.42 |
| Phi + gradient after a material change (K as the affine sum, re-factorized) | 0.7838 | 29.83 |
| Phi + gradient after a material change (K as the affine sum, CG on the held factors) | 0.3314 | 12.61 |
| Phi (taped, includes taping: LinearProblem.solve + assemble_scalar) | 0.8678 | 33.03 |
| Phi (taped, ReducedFunctional replay) | 0.8563 | 32.59 |
| Phi + gradient (taped: ReducedFunctional call + derivative) | 1.6992 | 64.67 |
| gradient (taped, tape exists: derivative alone) | 0.8508 | 32.38 |

Hand Phi + gradient is ~2x hand Phi (one extra back-solve) and 29-34x faster than the
taped Phi + gradient, which pays an assembly and a MUMPS factorization in both its forward
and its adjoint solve. After a material change, against the taped Phi + gradient: 0.51-0.53x
re-assembled and re-factorized, 0.46-0.47x as the affine sum re-factorized, 0.20x on the
held factors.
"""

import dolfinx_solver  # noqa: F401  (must precede dolfinx / petsc4py: sets up MPI and PETSc)

from importlib.metadata import version

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

import dolfinx
import dolfinx.fem.petsc
import ufl
import pyadjoint
import dolfinx_adjoint as dxa
from forward import best_of  # benchmarks/ is the script's folder: the median of 3

LU = {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}
E, NU = 10.0, 0.3
MU, LMBDA = E / (2 * (1 + NU)), E * NU / ((1 + NU) * (1 - 2 * NU))
TOP = 1


# --- the problem, shared by both methods -------------------------------------------------
comm = MPI.COMM_WORLD
assert comm.size == 1, "serial benchmark: the hand adjoint below uses local arrays"
mesh = dolfinx.mesh.create_box(comm, [[0, 0, 0], [1.5, 1, 1]], [13, 9, 9])
fdim = mesh.topology.dim - 1
top_facets = dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[2], 1))
tags = dolfinx.mesh.meshtags(mesh, fdim, top_facets, np.full(len(top_facets), TOP, np.int32))
ds_top = ufl.Measure("ds", domain=mesh, subdomain_data=tags)(TOP)

V = dolfinx.fem.functionspace(mesh, ("Lagrange", 2, (3,)))   # displacement
Vg = dolfinx.fem.functionspace(mesh, ("Lagrange", 1, (3,)))  # traction (only top dofs matter)
bottom = dolfinx.fem.locate_dofs_topological(
    V, fdim, dolfinx.mesh.locate_entities_boundary(mesh, fdim, lambda x: np.isclose(x[2], 0)))
bc = dolfinx.fem.dirichletbc(np.zeros(3), bottom, V)

u_, v = ufl.TrialFunction(V), ufl.TestFunction(V)


strain = ufl.sym(ufl.grad(u_))
a = ufl.inner(2 * MU * strain + LMBDA * ufl.tr(strain) * ufl.Identity(3), ufl.grad(v)) * ufl.dx


def known_traction(x):  # smooth, mostly compressive load on the top
    return np.vstack([0.2 * x[1], 0.1 * x[0] * x[1], -(1 + 0.5 * np.sin(2 * x[0]))])


# --- hand-written adjoint ----------------------------------------------------------------
a_form = dolfinx.fem.form(a)
K = dolfinx.fem.petsc.assemble_matrix(a_form, bcs=[bc])  # symmetric: diag 1 on bc
K.assemble()
B = dolfinx.fem.petsc.assemble_matrix(  # b = B g; bc rows zeroed so b vanishes on the clamp
    dolfinx.fem.form(ufl.inner(ufl.TrialFunction(Vg), v) * ds_top), bcs=[bc])
B.assemble()
M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.inner(u_, v) * ds_top))  # misfit mass
M.assemble()
ksp = PETSc.KSP().create(comm)
ksp.setOptionsPrefix("hand_")
opts = PETSc.Options()
for key, value in LU.items():
    opts[f"hand_{key}"] = value
ksp.setOperators(K)
ksp.setFromOptions()
ksp.setUp()  # the one factorization every hand-written Phi and gradient below reuses
b, u, lam, Md, u_target_vec = (K.createVecRight() for _ in range(5))
grad_hand = B.createVecRight()


def hand_phi(g_vec, solver=None):
    B.mult(g_vec, b)
    (solver or ksp).solve(b, u)     # back-solve only: factors cached
    u.axpy(-1.0, u_target_vec)      # u now holds u - u_target
    M.mult(u, Md)
    return 0.5 * u.dot(Md)


def hand_phi_and_gradient(g_vec, solver=None):
    phi = hand_phi(g_vec, solver)
    bc.set(Md.array_w, alpha=0.0)   # adjoint RHS vanishes on the clamp too
    (solver or ksp).solve(Md, lam)  # K^T = K: same factors
    B.multTranspose(lam, grad_hand)
    return phi


# --- the toolkit's own path after a material change (model/stiffness.py, model/solvers.py):
# K = mu A + lam B from matrices assembled once (A: 2 eps(u):grad v with the clamp's unit
# diagonal, B: div u div v without it), then either a new factorization or, for a change
# within NEARBY_RATIO, CG preconditioned by the factors already held (NearbySolver).
SAME = PETSc.Mat.Structure.SAME_NONZERO_PATTERN
A_mu = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.inner(2 * strain, ufl.grad(v)) * ufl.dx), bcs=[bc])
A_mu.assemble()
B_lam = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(ufl.tr(strain) * ufl.div(v) * ufl.dx), bcs=[bc],
                                          diag=0.0)
B_lam.assemble()
E_NEW, NU_NEW = 12.0, 0.32  # the material change timed below
MU_NEW, LMBDA_NEW = E_NEW / (2 * (1 + NU_NEW)), E_NEW * NU_NEW / ((1 + NU_NEW) * (1 - 2 * NU_NEW))


def affine_sum(mu, lmbda, out):
    out.zeroEntries()
    out.axpy(mu, A_mu, structure=SAME)
    out.axpy(lmbda, B_lam, structure=SAME)


def solver_of(matrix, prefix, options):
    solver = PETSc.KSP().create(comm)
    solver.setOptionsPrefix(prefix)
    for key, value in options.items():
        opts[f"{prefix}{key}"] = value
    solver.setOperators(matrix)
    solver.setFromOptions()
    return solver


class HeldFactors:  # CG's preconditioner: a back-solve through the factors of K at (E, NU)
    def apply(self, pc, x, y):
        ksp.solve(x, y)


K_new = A_mu.copy()
affine_refactorized = solver_of(K_new, "affine_", LU)
K_near = A_mu.copy()
nearby = solver_of(K_near, "nearby_", {"ksp_type": "cg", "ksp_rtol": 1e-8, "ksp_norm_type": "unpreconditioned"})
nearby.getPC().setType(PETSc.PC.Type.PYTHON)
nearby.getPC().setPythonContext(HeldFactors())


g_true = dolfinx.fem.Function(Vg)
g_true.interpolate(known_traction)
B.mult(g_true.x.petsc_vec, b)
ksp.solve(b, u_target_vec)
g_hand = dolfinx.fem.Function(Vg)
g_hand.x.array[:] = 0.5 * g_true.x.array  # evaluate away from the optimum

# --- taped: dolfinx-adjoint -------------------------------------------------------------
g = dxa.Function(Vg, name="g")
g.x.array[:] = g_hand.x.array
u_target = dxa.Function(V, name="u_target")
u_target.x.array[:] = u_target_vec.array
problem = dxa.LinearProblem(a, ufl.inner(g, v) * ds_top, bcs=[bc], petsc_options_prefix="taped_",
                            petsc_options=LU, adjoint_petsc_options=LU)
tape = pyadjoint.get_working_tape()


def taped_forward():  # a fresh tape each run: this is the "record" cost
    tape.clear_tape()
    uh = problem.solve()
    return dxa.assemble_scalar(0.5 * ufl.inner(uh - u_target, uh - u_target) * ds_top)


taped_forward()  # JIT-compile all forms before timing
t_tape = best_of(taped_forward)
J = taped_forward()
rf = pyadjoint.ReducedFunctional(J, pyadjoint.Control(g))


def taped_phi_and_gradient():
    rf(g)
    return rf.derivative()


taped_phi_and_gradient()  # builds and compiles the adjoint forms and solver
t_replay = best_of(lambda: rf(g))
t_taped_both = best_of(taped_phi_and_gradient)
t_taped_grad = best_of(rf.derivative)

# --- correctness ---------------------------------------------------------------------------
phi_hand = hand_phi_and_gradient(g_hand.x.petsc_vec)
grad_h = grad_hand.array.copy()
grad_t = np.asarray(rf.derivative().x.array[: len(grad_h)])
direction = dolfinx.fem.Function(Vg)
direction.x.array[:] = np.random.default_rng(0).standard_normal(len(grad_h))
eps = 1e-3  # Phi is quadratic in g, so the central difference is exact up to round-off
plus, minus = g_hand.copy(), g_hand.copy()
plus.x.array[:] += eps * direction.x.array
minus.x.array[:] -= eps * direction.x.array
fd = (hand_phi(plus.x.petsc_vec) - hand_phi(minus.x.petsc_vec)) / (2 * eps)
print(f"P2 box 13x9x9: {V.dofmap.index_map.size_global * 3} DOFs, "
      f"{Vg.dofmap.index_map.size_global * 3} traction DOFs, {len(top_facets)} top facets")
print(f"dolfinx {dolfinx.__version__}, dolfinx-adjoint {version('dolfinx-adjoint')}, "
      f"pyadjoint-ad {version('pyadjoint-ad')}")
print(f"Phi hand {phi_hand:.10e}, taped {float(J):.10e}")
print(f"|grad_hand - grad_taped| / |grad_hand| = "
      f"{np.linalg.norm(grad_h - grad_t) / np.linalg.norm(grad_h):.2e}")
print(f"finite difference along a random direction: FD {fd:.10e}, hand {grad_h @ direction.x.array:.10e}, "
      f"taped {grad_t @ direction.x.array:.10e}")


def hand_cold():  # what the hand path costs if K had to be re-assembled (e.g. new E, nu)
    K.zeroEntries()
    dolfinx.fem.petsc.assemble_matrix(K, a_form, bcs=[bc])
    K.assemble()  # new state: the next solve re-factorizes
    hand_phi_and_gradient(g_hand.x.petsc_vec)


def hand_affine_refactorized():  # new (E, nu): K as the affine sum, factorized again
    affine_sum(MU_NEW, LMBDA_NEW, K_new)
    hand_phi_and_gradient(g_hand.x.petsc_vec, affine_refactorized)


def hand_affine_nearby():  # new (E, nu): K as the affine sum, CG on the factors held at (E, NU)
    affine_sum(MU_NEW, LMBDA_NEW, K_near)
    hand_phi_and_gradient(g_hand.x.petsc_vec, nearby)


hand_affine_refactorized()
grad_refactorized = grad_hand.array.copy()
hand_affine_nearby()
apart = np.linalg.norm(grad_hand.array - grad_refactorized) / np.linalg.norm(grad_refactorized)
print(f"at E {E_NEW}, nu {NU_NEW}: the gradient on held factors (CG, {nearby.getIterationNumber()} iterations) "
      f"against a new factorization: {apart:.1e}")

# --- timings -------------------------------------------------------------------------------
t_cold = best_of(hand_cold)
t_affine = best_of(hand_affine_refactorized)
t_nearby = best_of(hand_affine_nearby)
t_phi = best_of(lambda: hand_phi(g_hand.x.petsc_vec))
t_both = best_of(lambda: hand_phi_and_gradient(g_hand.x.petsc_vec))
rows = [
    ("Phi (hand, cached factorization)", t_phi),
    ("Phi + gradient (hand)", t_both),
    ("Phi + gradient (hand, re-assembling and re-factorizing K first)", t_cold),
    ("Phi + gradient after a material change (the toolkit's: K as the affine sum, re-factorized)", t_affine),
    ("Phi + gradient after a material change (the toolkit's: K as the affine sum, CG on the held factors)", t_nearby),
    ("Phi (taped, includes taping: LinearProblem.solve + assemble_scalar)", t_tape),
    ("Phi (taped, ReducedFunctional replay)", t_replay),
    ("Phi + gradient (taped: ReducedFunctional call + derivative)", t_taped_both),
    ("gradient (taped, tape exists: derivative alone)", t_taped_grad),
]
print("\n| quantity | seconds | ratio to Phi (hand) |\n|---|---|---|")
for name, seconds in rows:
    print(f"| {name} | {seconds:.4f} | {seconds / t_phi:.2f} |")
print(f"\nhand Phi+gradient / hand Phi = {t_both / t_phi:.2f}; taped Phi+gradient / taped Phi (replay) = "
      f"{t_taped_both / t_replay:.2f}; taped Phi+gradient / hand Phi+gradient = {t_taped_both / t_both:.1f}")
print(f"after a material change, ours / taped Phi+gradient: re-assembled and re-factorized {t_cold / t_taped_both:.2f}, "
      f"the affine sum re-factorized {t_affine / t_taped_both:.2f}, the affine sum on held factors "
      f"{t_nearby / t_taped_both:.2f}")
