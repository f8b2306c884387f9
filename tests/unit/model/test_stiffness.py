"""K(theta) (stiffness.py): the affine sum and the one-matrix K at fixed materials are
the same operator, and a simulation holds the one matrix only."""

import numpy as np
import pytest

from fenics_elasto.model.elasticity import ElasticModel
from fenics_elasto.model.scene import load_scene
from fenics_elasto.model.simulate import material_values, simulate


@pytest.fixture(scope="module")
def phantom_p1(scenes):
    """The 3D phantom at P1: several regions, each its own pair of affine terms."""
    return load_scene(scenes["prostate-phantom"], ["degree=1"])


def test_fixed_stiffness_is_the_affine_sum_at_its_materials(phantom_p1):
    E, nu = material_values(phantom_p1)
    affine = ElasticModel(phantom_p1).stiffness
    fixed = ElasticModel(phantom_p1, fixed=(E, nu)).stiffness
    summed = affine.matrix(affine.coefficients(E, nu))
    one = fixed.matrix(fixed.coefficients(E, nu))
    summed.axpy(-1.0, one)
    assert summed.norm() < 1e-12 * one.norm()
    assert len(fixed.terms) == 1 and len(affine.terms) == 2 * len(phantom_p1.materials)


def test_k_at_once_is_the_constrained_sum_in_its_pattern(phantom_p1):
    """at_once (a factorization started before the terms exist): K in one pass equals
    the terms' constrained sum, and shares its pattern, so the solver holding it is
    refilled from the terms in place at other materials; the terms then reuse its
    pattern matrix instead of making their own."""
    E, nu = material_values(phantom_p1)
    model = ElasticModel(phantom_p1)
    stiffness, clamped = model.stiffness, model.dofs.clamped_dofs(phantom_p1.fixed)
    c = stiffness.coefficients(E, nu)
    K = stiffness.at_once(c, clamped)
    assert "_assembled" not in vars(stiffness) and stiffness._pattern is not None
    summed = stiffness.constrained(c, clamped)
    assert stiffness._pattern is None  # taken over by the terms
    assert K.getInfo()["nz_allocated"] == summed.getInfo()["nz_allocated"]
    summed.axpy(-1.0, K)
    assert summed.norm() < 1e-13 * K.norm()
    stiffness.constrained(2.0 * c, clamped, out=K)  # same pattern: refilled in place
    K.axpy(-1.0, stiffness.constrained(2.0 * c, clamped))
    assert K.norm() == 0.0


def test_simulation_with_its_own_model_equals_a_shared_affine_one(phantom_p1):
    own = simulate(phantom_p1)
    shared = simulate(phantom_p1, ElasticModel(phantom_p1))
    assert len(own.model.stiffness.terms) == 1
    difference = np.abs(own.u.x.array - shared.u.x.array).max()
    assert difference < 1e-9 * np.abs(shared.u.x.array).max()


def test_fixed_stiffness_refuses_other_materials(phantom_p1):
    E, nu = material_values(phantom_p1)
    fixed = ElasticModel(phantom_p1, fixed=(E, nu)).stiffness
    with pytest.raises(ValueError, match="fixed at"):
        fixed.coefficients(2 * E, nu)
    with pytest.raises(TypeError, match="no derivatives"):
        fixed.coefficient_derivatives(E, nu)


def test_new_materials_reuse_the_compiled_form(phantom_p1):
    """The Lame values are constants of the form, not literals compiled into it: K at
    other materials is the same kernel (no JIT compile) and scales with E as it must."""
    import dolfinx.fem.petsc

    from fenics_elasto.model.stiffness import stiffness_form

    E, nu = material_values(phantom_p1)
    V = ElasticModel(phantom_p1).dofs.V
    forms = [stiffness_form(phantom_p1, V, scale * E, nu) for scale in (1.0, 2.5)]
    assert forms[0].module is forms[1].module
    K1, K2 = (dolfinx.fem.petsc.assemble_matrix(form) for form in forms)
    K1.assemble()
    K2.assemble()
    K2.axpy(-2.5, K1)
    assert K2.norm() < 1e-12 * K1.norm() * 2.5


def test_the_kernel_flags_change_round_off_only_and_yield_to_the_users(scenes, monkeypatch):
    """KERNEL_FLAGS reorder the kernels' sums: K equals the one compiled with dolfinx's
    own arguments to round-off, on curved cells (the phantom at P2, where the quadrature
    loops are longest). A user's own compiler arguments are left alone."""
    import dolfinx.fem.petsc
    import dolfinx.jit

    from fenics_elasto.model import stiffness

    scene = load_scene(scenes["prostate-phantom"], ["degree=2"])
    E, nu = material_values(scene)
    V = ElasticModel(scene).dofs.V
    plain = {"cffi_extra_compile_args": stiffness.dolfinx_compile_args()}
    assert stiffness.kernel_options()["cffi_extra_compile_args"][-len(stiffness.KERNEL_FLAGS):] == stiffness.KERNEL_FLAGS
    ours, theirs = stiffness.stiffness_form(scene, V, E, nu), stiffness.stiffness_form(scene, V, E, nu, plain)
    assert ours.module is not theirs.module
    K, reference = (dolfinx.fem.petsc.assemble_matrix(form) for form in (ours, theirs))
    K.assemble()
    reference.assemble()
    K.axpy(-1.0, reference)
    assert K.norm() < 1e-13 * reference.norm()  # other code, the same matrix
    monkeypatch.setattr(dolfinx.jit, "get_options", lambda: {"cffi_extra_compile_args": ["-O1"]})
    assert stiffness.kernel_options() == {}


@pytest.mark.parametrize("threads", ["1", "2", "3"])
def test_block_products_equal_the_matrix_product_column_by_column(phantom_p1, threads, monkeypatch):
    """times_block, by every path it takes (one rank: a wide row-major block through
    scipy, in slabs of rows on this many threads; a column-major block, as PETSc's dense
    arrays are, and a narrow one through PETSc, MULTIPLY_COLUMNS at a time): PETSc's own
    matrix-vector product, column for column, in the block's memory order."""
    monkeypatch.setenv("OMP_NUM_THREADS", threads)
    from fenics_elasto.model.dofs import MULTIPLY_COLUMNS, SCIPY_COLUMNS, times_block

    model = ElasticModel(phantom_p1)
    M = model.stiffness.terms[0]
    x, y = M.createVecs()
    for width, order in ((2 * MULTIPLY_COLUMNS + 5, "C"), (2 * MULTIPLY_COLUMNS + 5, "F"), (SCIPY_COLUMNS - 1, "C")):
        Y = np.asarray(np.random.default_rng(0).standard_normal((model.dofs.owned, width)), order=order)
        exact = np.empty_like(Y)
        for j in range(width):
            x.array[:] = Y[:, j]
            M.mult(x, y)
            exact[:, j] = y.array_r
        product = times_block(M, Y)
        assert product.flags[f"{order}_CONTIGUOUS"]
        assert np.allclose(product, exact, rtol=0, atol=1e-12 * np.abs(exact).max())
