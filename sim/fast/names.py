"""The names of the machinery's choices a scenario may make: the linear solvers of ``sim.fast.solvers`` and the
precision of their factorisation. Plain tuples, so that the scenario checks a choice without loading a solver."""

LINEAR_SOLVERS = ("auto", "pardiso", "superlu")
PRECISIONS = ("mixed", "double")
