"""Sparse linear algebra of normal matrices: block patterns and assembly (:mod:`.blocks`), the
sparse Cholesky interface (:mod:`.cholesky`) and its CHOLMOD implementation (:mod:`.cholmod`),
fill-reducing orderings (:mod:`.ordering`), selected inversion (:mod:`.selinv`), banded joint
covariances and their completion (:mod:`.banded`), the covariance skeleton of a sparse prior
(:mod:`.skeleton`), LAPACK for the compiled kernels (:mod:`.lapack`), per-matrix functions
of stacks with runs of equal matrices (:mod:`.runs`)."""
