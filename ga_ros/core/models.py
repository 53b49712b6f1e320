"""Constraint models ``f(l, x) = 0`` of the mixed adjustment, vectorised over connections.

Each model evaluates, for ``m`` connections at the linearisation point ``(l0, x0)``,
the misclosure ``f`` and the Jacobians ``A = df/dx`` (w.r.t. the two nodes) and ``B = df/dl``
(docs/method.md Sec. 2, paper eqs. 6-8).

* ``se3`` (product default): unknowns are full poses ``T_i`` (6 per node, right perturbation
  ``T_i exp(d_i)``, ``d = [rho, phi]``); the observation is the motion ``T_ij`` parametrised by its
  right perturbation ``v`` around the measured value, ``T_ij(l) = T_ij_meas exp(v)``, and
  ``f = log(T_ij(l)^-1 T_i^-1 T_j)`` (6 equations). Since ``f = 0`` forces
  ``v = log(T_ij_meas^-1 T_i^-1 T_j)``, the adjustment minimises exactly the g2o/GTSAM cost.
* ``se2``: the ``se3`` model of planar poses (2-D graphs): unknowns are ``[x, y, theta]`` per
  node (right perturbation), the observation is the planar part ``[x y rz]`` of the motion's
  perturbation ``v``, ``f = log(T_ij(l)^-1 T_i^-1 T_j)`` in SE(2) (3 equations). On planar poses
  this is the ``se3`` model restricted to the plane (se(2) is a subalgebra of se(3)), with half
  the unknowns; the connection covariance used is the ``[x y rz]`` block of the 6x6 one.
* ``paper`` (eq. 1): unknowns are 3-D positions ``p_i``; ``l = [t, w]`` and
  ``f = p_j - R(w) p_i - t`` (3 equations per connection, 6 observations).
* ``linear``: unknowns are positions, ``f = p_j - p_i - t`` (the paper's model with ``R = I``):
  linear in both ``l`` and ``x``, used where an exact closed-form answer is wanted.

Each model is a :class:`ConstraintModel` (:class:`Se3Model`, :class:`Se2Model`,
:class:`PositionModel`, :class:`LinearModel`), registered in :data:`MODELS` under the name
``SolverConfig.model`` takes; :func:`model_of` looks one up. The module-level functions
(:func:`dof`, :func:`linearise`, ...) take the name, for callers that hold only the setting.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import columns
from ga_ros.errors import InputError
from ga_ros.geometry import se2, se3, so3


@dataclass(frozen=True)
class Linearisation:
    """Per-connection misclosure and Jacobians at one linearisation point.

    Attributes
    ----------
    f : (m, r) misclosure ``f(l0, x0)``.
    A_src, A_dst : (m, r, d) ``df/dx`` w.r.t. the source and destination node.
    B : (m, r, 6) ``df/dl`` w.r.t. the connection's 6 observations.
    """

    f: FloatArray
    A_src: FloatArray
    A_dst: FloatArray
    B: FloatArray


@dataclass(frozen=True)
class Between:
    """Misclosure of measured motions and its Jacobians (``se3`` / ``se2``).

    ``e = log(T_meas^-1 T_i^-1 T_j)``; for the right perturbations ``T_i exp(d_i)``,
    ``T_j exp(d_j)``: ``de/dd_j = Jr_inv`` and ``de/dd_i = -Jr_inv @ Ad_ji``.

    Attributes
    ----------
    e : (m, d) misclosure.
    Jr_inv : (m, d, d) ``J_r(e)^-1``.
    Ad_ji : (m, d, d) ``Ad(T_ij^-1)``.
    """

    e: FloatArray
    Jr_inv: FloatArray
    Ad_ji: FloatArray


class ConstraintModel(ABC):
    """A constraint model ``f(l, x) = 0`` of the mixed adjustment (see the module docstring).

    Attributes
    ----------
    name : the registry key (``SolverConfig.model``).
    dof : unknowns per node (= constraint equations per connection).
    observations : observations per connection (``o``: 3 for se2's ``[x y rz]``, else 6).
    motion : the observation is the right perturbation of a measured motion (g2o/GTSAM cost):
        the solver's Gauss-Newton shortcut applies and the residuals after a step are the
        misclosure (:func:`motion_misclosure`).
    compiled : the solver has compiled (numba) kernels and a column form of it (se3).
    """

    name: ClassVar[str]
    dof: ClassVar[int]
    observations: ClassVar[int] = 6
    motion: ClassVar[bool] = False
    compiled: ClassVar[bool] = False

    @property
    def equations(self) -> int:
        """Constraint equations per connection."""
        return self.dof

    def observation_covariance(self, cov: FloatArray) -> FloatArray:
        """The covariance ``(m, o, o)`` of the connections' observations from their 6x6 ``cov``
        (m, rad)."""
        return cov

    @abstractmethod
    def linearise(self, T: FloatArray, src: IntArray, dst: IntArray, z_b: FloatArray,
                  v: FloatArray) -> Linearisation:
        """Misclosure and Jacobians of all connections (see :func:`linearise`)."""

    def retract(self, T: FloatArray, idx: IntArray, d: FloatArray) -> FloatArray:
        """Apply increments ``d`` (k, dof) to nodes ``idx``: positions ``p + d``."""
        out = T.copy()
        out[idx, :3, 3] += d
        return out

    def prior_residual(self, T: FloatArray, T_mean: FloatArray
                       ) -> tuple[FloatArray, FloatArray]:
        """Residual ``e = p - p_mean`` (k, 3) of a weighted parameter and its Jacobian."""
        e = T[:, :3, 3] - T_mean[:, :3, 3]
        return e, np.broadcast_to(np.eye(3), (e.shape[0], 3, 3)).copy()

    def motion_misclosure(self, T: FloatArray, src: IntArray, dst: IntArray,
                          T_meas: FloatArray) -> FloatArray:
        """``e = log(T_meas^-1 T_i^-1 T_j)`` ``(m, dof)`` (motion models only)."""
        raise InputError(f'the {self.name} model observes no motions')

    def between(self, T: FloatArray, src: IntArray, dst: IntArray, T_meas: FloatArray,
                Tm_inv: FloatArray | None = None) -> Between:
        """Misclosure and Jacobians of measured motions (motion models only)."""
        raise InputError(f'the {self.name} model observes no motions')

    def __repr__(self) -> str:
        return f'{type(self).__name__}()'


class Se3Model(ConstraintModel):
    """Full poses (6 unknowns per node), the product default."""

    name = 'se3'
    dof = 6
    motion = True
    compiled = True

    def linearise(self, T: FloatArray, src: IntArray, dst: IntArray, z_b: FloatArray,
                  v: FloatArray) -> Linearisation:
        T_meas = se3.from_translation_rotvec(z_b[:, :3], z_b[:, 3:])
        T_i, T_j = T[src], T[dst]
        T_ij = se3.inverse(T_i) @ T_j
        F = se3.exp(-v) @ se3.inverse(T_meas) @ T_ij
        f = se3.log(F)
        Jl_inv = se3.left_jacobian_inv(f)
        Jr_inv = Jl_inv @ se3.adjoint(F)  # J_l(f) = Ad(exp f) J_r(f) and exp(f) = F
        A_dst = Jr_inv
        # T_i exp(d): F -> F exp(-Ad(T_ij^-1) d)
        A_src = -Jr_inv @ se3.adjoint(se3.inverse(T_ij))
        # exp(-(v + d)) -> F -> exp(-Ad(exp(-v)) J_l(v) d) F = exp(-J_r(v) d) F
        B = -Jl_inv
        if np.any(v):
            B = B @ se3.right_jacobian(v)
        return Linearisation(f, A_src, A_dst, B)

    def retract(self, T: FloatArray, idx: IntArray, d: FloatArray) -> FloatArray:
        out = T.copy()
        out[idx] = columns.retract(T[idx], d)  # se3.retract, in columns (~4x faster)
        return out

    def prior_residual(self, T: FloatArray, T_mean: FloatArray
                       ) -> tuple[FloatArray, FloatArray]:
        R_rel = np.swapaxes(T_mean[:, :3, :3], 1, 2) @ T[:, :3, :3]
        phi = so3.log(R_rel)
        J = np.zeros((phi.shape[0], 6, 6))
        J[:, :3, :3] = R_rel
        J[:, 3:, 3:] = so3.right_jacobian_inv(phi)
        dp = T[:, :3, 3] - T_mean[:, :3, 3]
        return np.hstack([np.einsum('kji,kj->ki', T_mean[:, :3, :3], dp), phi]), J

    def motion_misclosure(self, T: FloatArray, src: IntArray, dst: IntArray,
                          T_meas: FloatArray) -> FloatArray:
        return se3.log(se3.inverse(T_meas) @ se3.inverse(T[src]) @ T[dst])

    def between(self, T: FloatArray, src: IntArray, dst: IntArray, T_meas: FloatArray,
                Tm_inv: FloatArray | None = None) -> Between:
        T_ij = se3.inverse(T[src]) @ T[dst]
        E = (se3.inverse(T_meas) if Tm_inv is None else Tm_inv) @ T_ij
        e = se3.log(E)
        # J_r(e)^-1 = J_l(e)^-1 Ad(exp e) (equal to J_l(-e)^-1, the kernels' form; this
        # product is kept because the window's seeded reference numbers are bit-identical
        # with it)
        return Between(e, se3.left_jacobian_inv(e) @ se3.adjoint(E),
                       se3.adjoint(se3.inverse(T_ij)))


class Se2Model(ConstraintModel):
    """Planar poses ``[x, y, theta]`` (3 unknowns per node) of 2-D graphs."""

    name = 'se2'
    dof = 3
    observations = 3
    motion = True

    def observation_covariance(self, cov: FloatArray) -> FloatArray:
        return np.ascontiguousarray(cov[:, se2.AXES[:, None], se2.AXES])

    def linearise(self, T: FloatArray, src: IntArray, dst: IntArray, z_b: FloatArray,
                  v: FloatArray) -> Linearisation:
        P = se2.Planar.from_matrix
        T_meas = P(se3.from_translation_rotvec(z_b[:, :3], z_b[:, 3:]))
        T_ij = P(T[src]).inverse().compose(P(T[dst]))
        F = P(se2.exp(-v)).compose(T_meas.inverse()).compose(T_ij)
        f = F.log()
        Jr_inv = se2.right_jacobian_inv(f)
        A_src = -Jr_inv @ se2.adjoint(T_ij.inverse())
        # exp(-(v + d)) F = exp(-J_r(v) d) exp(-v) F, and exp(g) F = F exp(Ad(F^-1) g):
        # df/dv = -J_r(f)^-1 Ad(F^-1) J_r(v) = -J_l(f)^-1 J_r(v)
        B = -Jr_inv @ se2.adjoint(F.inverse()) @ np.linalg.inv(se2.right_jacobian_inv(v))
        return Linearisation(f, A_src, Jr_inv, B)

    def retract(self, T: FloatArray, idx: IntArray, d: FloatArray) -> FloatArray:
        out = T.copy()
        out[idx] = se2.retract(T[idx], d)
        return out

    def prior_residual(self, T: FloatArray, T_mean: FloatArray
                       ) -> tuple[FloatArray, FloatArray]:
        e = se2.local(T_mean, T)
        return e, se2.right_jacobian_inv(e)

    def motion_misclosure(self, T: FloatArray, src: IntArray, dst: IntArray,
                          T_meas: FloatArray) -> FloatArray:
        P = se2.Planar.from_matrix(T)  # the nodes' components first, then gathered
        return se2.Planar.from_matrix(T_meas).inverse().compose(
            P.take(src).inverse().compose(P.take(dst))).log()

    def between(self, T: FloatArray, src: IntArray, dst: IntArray, T_meas: FloatArray,
                Tm_inv: FloatArray | None = None) -> Between:
        P = se2.Planar.from_matrix(T)
        T_ij = P.take(src).inverse().compose(P.take(dst))
        e = se2.Planar.from_matrix(T_meas).inverse().compose(T_ij).log()
        return Between(e, se2.right_jacobian_inv(e), se2.adjoint(T_ij.inverse()))


class PositionModel(ConstraintModel):
    """The paper's eq. 1 (``'paper'``): 3-D positions, ``f = p_j - R(w) p_i - t``."""

    name = 'paper'
    dof = 3

    def linearise(self, T: FloatArray, src: IntArray, dst: IntArray, z_b: FloatArray,
                  v: FloatArray) -> Linearisation:
        l0 = z_b + v
        t, w = l0[:, :3], l0[:, 3:]
        R = so3.exp(w)
        p_i, p_j = T[src, :3, 3], T[dst, :3, 3]
        f = p_j - (R @ p_i[:, :, None])[:, :, 0] - t
        m = src.shape[0]
        A_src = -R
        A_dst = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
        B = np.zeros((m, 3, 6))
        B[:, :, :3] = -np.eye(3)
        # d(R(w) p)/dw = -R [p]x J_r(w)  =>  df/dw = R [p]x J_r(w)
        B[:, :, 3:] = R @ so3.hat(p_i) @ so3.right_jacobian(w)
        return Linearisation(f, A_src, A_dst, B)


class LinearModel(PositionModel):
    """Positions with ``R = I`` (``'linear'``): ``f = p_j - p_i - t``, linear in ``l`` and
    ``x``."""

    name = 'linear'

    def linearise(self, T: FloatArray, src: IntArray, dst: IntArray, z_b: FloatArray,
                  v: FloatArray) -> Linearisation:
        l0 = z_b + v
        f = T[dst, :3, 3] - T[src, :3, 3] - l0[:, :3]
        m = src.shape[0]
        eye = np.broadcast_to(np.eye(3), (m, 3, 3))
        B = np.zeros((m, 3, 6))
        B[:, :, :3] = -np.eye(3)
        return Linearisation(f, -eye.copy(), eye.copy(), B)


#: The constraint models by name (``SolverConfig.model``).
MODELS: dict[str, ConstraintModel] = {m.name: m for m in (Se3Model(), Se2Model(),
                                                          PositionModel(), LinearModel())}
MODEL_NAMES = tuple(MODELS)
#: Models whose observation is the right perturbation of a measured motion (g2o/GTSAM cost).
MOTION_MODELS = tuple(name for name, m in MODELS.items() if m.motion)


def model_of(model: str | ConstraintModel) -> ConstraintModel:
    """The registered model of a name (a model is returned as it is).

    Raises
    ------
    InputError
        An unknown name (the message lists :data:`MODEL_NAMES`).
    """
    if isinstance(model, ConstraintModel):
        return model
    try:
        return MODELS[model]
    except (KeyError, TypeError):
        raise InputError(f'unknown constraint model {model!r}; use one of {MODEL_NAMES}') from None


def check_model(model: str) -> None:
    """Raise :class:`InputError` unless ``model`` is a registered name."""
    model_of(model)


def dof(model: str) -> int:
    """Unknowns per node: 6 for ``se3``, 3 for ``se2``, ``paper`` and ``linear``."""
    return model_of(model).dof


def equations_per_connection(model: str) -> int:
    """Constraint equations per connection: 6 for ``se3``, 3 for the others."""
    return model_of(model).equations


def observations_per_connection(model: str) -> int:
    """Observations per connection: 3 for ``se2`` (``[x y rz]``), 6 for the others."""
    return model_of(model).observations


def observation_covariance(model: str, cov: FloatArray) -> FloatArray:
    """The covariance of a connection's observations: the ``[x y rz]`` block of the 6x6
    ``cov`` (m, rad) for ``se2``, ``cov`` itself for the other models."""
    return model_of(model).observation_covariance(cov)


def motion_misclosure(model: str, T: FloatArray, src: IntArray, dst: IntArray,
                      T_meas: FloatArray) -> FloatArray:
    """``e = log(T_meas^-1 T_i^-1 T_j)`` ``(m, d)`` of the motion models (se3: 6, se2: 3)."""
    return model_of(model).motion_misclosure(T, src, dst, T_meas)


def between(model: str, T: FloatArray, src: IntArray, dst: IntArray,
            T_meas: FloatArray, Tm_inv: FloatArray | None = None) -> Between:
    """Misclosure and Jacobians of measured motions (see :class:`Between`) for se3 / se2.

    ``Tm_inv`` (se3): the inverses of ``T_meas`` when the caller keeps them (a solver
    linearising many times), else they are computed here.
    """
    return model_of(model).between(T, src, dst, T_meas, Tm_inv)


def linearise(model: str, T: FloatArray, src: IntArray, dst: IntArray, z_b: FloatArray,
              v: FloatArray) -> Linearisation:
    """Misclosure and Jacobians of all connections.

    Parameters
    ----------
    model : 'se3' | 'se2' | 'paper' | 'linear'.
    T : (n, 4, 4) current node poses ``T_world_node`` (positions only are used by paper/linear).
    src, dst : (m,) node indices.
    z_b : (m, 6) measured observations ``[t, w]`` (m, rad).
    v : (m, o) current residuals (adjusted observations ``l0 = l_b + v``), ``o`` =
        :func:`observations_per_connection` (se2: the ``[x y rz]`` perturbation).
    """
    return model_of(model).linearise(T, src, dst, z_b, v)


def retract(model: str, T: FloatArray, idx: IntArray, d: FloatArray) -> FloatArray:
    """Apply increments ``d`` (k, dof) to nodes ``idx``: ``T exp(d)`` (se3, se2) or ``p + d``."""
    return model_of(model).retract(T, idx, d)


def prior_residual(model: str, T: FloatArray, T_mean: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Residual ``e`` (k, d) and Jacobian ``de/dx`` (k, d, d) of a weighted parameter.

    ``se3``: position and rotation apart, ``e = [R_mean' (p - p_mean), log(R_mean' R)]``, with
    Jacobian ``diag(R_mean' R, J_r(phi)^-1)`` for the right perturbation ``T exp(d)`` (equal to
    the tangent ``log(T_mean^-1 T)`` to first order; see ``refinement.tangent_prior`` for why);
    ``se2``: ``e = log(T_mean^-1 T)`` with Jacobian ``J_r(e)^-1``; positions: ``e = p - p_mean``.
    """
    return model_of(model).prior_residual(T, T_mean)
