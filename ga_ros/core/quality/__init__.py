"""Statistical quality control of an adjustment (Baarda's testing and reliability theory).

Given a network, the solution of :func:`ga_ros.core.solver.solve` and the priors it used, this
module computes, for the mixed (Gauss-Helmert) model of docs/method.md Sec. 2:

* the **global test** of the variance factor (Koch 1999, Sec. 4.3; Leick, *GPS Satellite
  Surveying*, Sec. 4.9): ``T = v' P v / sigma_prior^2 ~ chi2(r - u)`` under ``H0``;
  rejected when ``T > chi2_{1-alpha}(r - u)`` (``sigma_prior = 1``: the covariances are
  taken as given);
* the **redundancy numbers** (Baarda 1968; Teunissen, *Testing Theory*, Sec. 4): the diagonal
  blocks of ``R = Q_vv P``. With ``M = B S B'``, ``G_i = A_i Q_x A_i'`` and
  ``Q_kk = M^-1 (M - A Q_x A') M^-1`` (cofactor of the Lagrange multipliers ``k``),
  the block of connection ``i`` is ``R_ii = S_i B_i' Q_kk,ii B_i`` and its trace is
  ``r_i = tr(I - M_i^-1 G_i)``. They sum to the redundancy ``r - u`` over connections and
  weighted parameters (priors). Only the blocks of ``Q_x = N^-1`` on connected node pairs are
  needed; they come from sparse solves with the Cholesky factor of ``N``, never a dense inverse;
* **standardised residuals and the w-test** (Baarda's data snooping, for correlated
  observations: Teunissen, Sec. 4.4): ``w_j = (P v)_j / sqrt((P Q_vv P)_jj)`` with
  ``P Q_vv P = B' Q_kk B``; ``w_j ~ N(0, 1)`` under ``H0``, critical value
  ``z_{1-alpha0/2}``;
* the **multi-dimensional test of a whole connection** (Teunissen, Sec. 4.3, ``q``-dimensional
  bias ``C_q nabla`` with ``C_q`` the connection's equations): ``T_i = k_i' Q_kk,ii^+ k_i``,
  ``chi2(q_i)`` under ``H0`` with ``q_i = rank(Q_kk,ii)`` (``q_i < r_c`` for a connection whose
  redundancy is partly zero; a bridge, ``r_i = 0``, cannot be tested);
* the **B-method** of testing (Baarda 1968): ``lambda0`` is the non-centrality that the 1-D
  test of level ``alpha0`` detects with power ``gamma0`` (Baarda's ``beta0``, default 0.80);
  the ``q``-dimensional test uses the level ``alpha_q`` that detects the same ``lambda0`` with
  the same power;
* the **minimal detectable bias** (internal reliability) of every observation component:
  ``|nabla_j| = sqrt(lambda0 / (P Q_vv P)_jj)`` (observation units, m or rad);
* **iterative data snooping** (:func:`data_snooping`): adjust, test every connection, remove the
  one with the largest test ratio, re-adjust (with :func:`ga_ros.core.solver.solve`) and repeat
  until no test rejects.

References: W. Baarda, *A testing procedure for use in geodetic networks*, Netherlands
Geodetic Commission, 1968; P.J.G. Teunissen, *Testing Theory*, Delft, 2000/2006;
E.M. Mikhail, *Observations and Least Squares*, 1976 (Ch. 5 and 9, the general model);
A. Leick, *GPS Satellite Surveying*, Ch. 4 (quality control).

The quality figures are those of the *least-squares* adjustment: a result solved with a robust
loss is re-assessed with unit weights.

The package: :mod:`.config` (:class:`QualityConfig`, the B-method's non-centralities),
:mod:`.cofactors` (blocks of ``Q_x`` and their propagation), :mod:`.reliability` (redundancy
numbers, w-tests and MDBs, connection tests), :mod:`.variance_factor` (the global test),
:mod:`.report` (:class:`QualityReport`, :class:`QualitySummary`), :mod:`.control`
(:func:`quality_control`, :func:`checked_solve`) and :mod:`.snooping` (:func:`data_snooping`).
"""

from ga_ros.core.quality.config import SNOOP_TESTS, QualityConfig, b_method_alpha, noncentrality
from ga_ros.core.quality.control import checked_solve, quality_control
from ga_ros.core.quality.report import QualityReport, QualitySummary, summarise
from ga_ros.core.quality.snooping import SnoopingResult, data_snooping

__all__ = [
    'SNOOP_TESTS',
    'QualityConfig',
    'QualityReport',
    'QualitySummary',
    'SnoopingResult',
    'b_method_alpha',
    'checked_solve',
    'data_snooping',
    'noncentrality',
    'quality_control',
    'summarise',
]
