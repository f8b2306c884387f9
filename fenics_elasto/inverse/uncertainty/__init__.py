"""How sure: the posterior of the estimated constants, profile-likelihood intervals, identifiability."""
