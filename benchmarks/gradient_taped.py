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

Measured on this machine (2026-11-26; 2 shared cores, serial; dolfinx 0.11.0.post0,
dolfinx-adjoint 0.4.0, pyadjoint-ad 2026.10.0). Gradients agree to 4.7e-15 (relative), and
both match a central finite difference along a random direction to 10 digits.

| quantity | seconds | ratio to Phi (hand) |
|---|---|---|
| Phi (hand, cached factorization) | 0.0365 | 1.00 |
| Phi + gradient (hand) | 0.0722 | 1.98 |
| Phi + gradient (hand, re-assembling and re-factorizing K first) | 1.7828 | 48.82 |
| Phi (taped, includes taping: LinearProblem.solve + assemble_scalar) | 1.7974 | 49.22 |
| Phi (taped, ReducedFunctional replay) | 1.8143 | 49.68 |
| Phi + gradient (taped: ReducedFunctional call + derivative) | 3.6943 | 101.16 |
| gradient (taped, tape exists: derivative alone) | 1.7947 | 49.14 |

Hand Phi + gradient is 1.98x hand Phi (exactly one extra back-solve) and 51x faster than the
taped Phi + gradient, which pays an assembly and a MUMPS factorization in both its forward
and its adjoint solve. Even re-factorizing every call, the hand path is 2x faster.
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


def hand_phi(g_vec):
    B.mult(g_vec, b)
    ksp.solve(b, u)                 # back-solve only: factors cached
    u.axpy(-1.0, u_target_vec)      # u now holds u - u_target
    M.mult(u, Md)
    return 0.5 * u.dot(Md)


def hand_phi_and_gradient(g_vec):
    phi = hand_phi(g_vec)
    bc.set(Md.array_w, alpha=0.0)   # adjoint RHS vanishes on the clamp too
    ksp.solve(Md, lam)              # K^T = K: same factors
    B.multTranspose(lam, grad_hand)
    return phi


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


# --- timings -------------------------------------------------------------------------------
t_cold = best_of(hand_cold)
t_phi = best_of(lambda: hand_phi(g_hand.x.petsc_vec))
t_both = best_of(lambda: hand_phi_and_gradient(g_hand.x.petsc_vec))
rows = [
    ("Phi (hand, cached factorization)", t_phi),
    ("Phi + gradient (hand)", t_both),
    ("Phi + gradient (hand, re-assembling and re-factorizing K first)", t_cold),
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
