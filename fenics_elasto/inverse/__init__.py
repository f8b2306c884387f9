"""The inverse problem: misfit, adjoint gradients, inner and outer optimisation, reduced bases, uncertainty."""
