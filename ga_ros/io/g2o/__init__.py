"""g2o pose-graph files: read into a :class:`ConnectionNetwork`, write back, evaluate the cost.

Supported lines (one record per line, fields separated by white space)::

    VERTEX_SE3:QUAT  id x y z qx qy qz qw
    EDGE_SE3:QUAT    i j [p] x y z qx qy qz qw  I11 I12 .. I16 I22 .. I66  (21 upper values)
    PARAMS_SE3OFFSET p x y z qx qy qz qw         (sensor offset T_robot_sensor, id p)
    VERTEX_SE2       id x y theta
    EDGE_SE2         i j [p] x y theta  I11 I12 I13 I22 I23 I33            (6 upper values)
    PARAMS_SE2OFFSET p x y theta
    VERTEX2          id x y theta                (TORO 2-D)
    EDGE2            i j x y theta  Iff Ifs Iss Irr Ifr Isr                (TORO order)
    FIX              id [id ...]

Blank lines and lines starting with ``#`` are skipped. An edge is the motion ``T_i_j`` of vertex
``j`` in the frame of vertex ``i`` with an information matrix ``Omega`` (inverse covariance); for
``EDGE_SE3:QUAT`` its order is ``[x y z qx qy qz]``, the same as ours ``[x y z rx ry rz]``. As in
GTSAM's g2o reader (and as the benchmark's reference optima assume, see
``shared/data/README.md``), the rotation block is taken as the information of the rotation vector
(rad), not of the quaternion's vector part (which would weigh rotations by 4).

Sensor offsets (what RTAB-Map and g2o itself write first): an identity ``PARAMS_*OFFSET`` is
accepted and written back. An edge that names a parameter id ``p`` measures the motion between
sensor frames, ``Z = S^-1 T_i^-1 T_j S`` with ``S = T_robot_sensor``; it is read as the robot-frame
motion ``T_meas = S Z S^-1`` with information ``Ad(S^-1)' Omega Ad(S^-1)`` (exactly the same cost,
since ``Log(S^-1 X S) = Ad(S^-1) Log(X)``), and written back in the sensor frame. A non-identity
offset that no edge names is refused: it is ambiguous whether the file's edges include it.

Files without any ``VERTEX`` line (edge-only benchmark files) are read with vertices in
increasing id order and ``has_guess = False``: see :mod:`ga_ros.core.initialization` for the
initial guess. Information matrices that are not positive definite are repaired by eigenvalue
clipping (:func:`ga_ros.core.covariance.nearest_positive_definite`) with one
:class:`InformationRepairWarning` per file listing the lines, or refused with ``strict=True``.

Cost convention (:func:`graph_cost`): ``sum_k e_k' Omega_k e_k`` with
``e_k = Log(T_meas^-1 T_i^-1 T_j)``, the full Lie-group logarithm (GTSAM's ``Pose3`` / ``Pose2``
local coordinates), ordered translation first (``[rho, phi]`` in 3-D, ``[rho_x, rho_y, theta]`` in
2-D). 2-D graphs are embedded in SE(3) (``z = 0``, rotation about ``z``); the out-of-plane
components ``z, rx, ry`` get unit information. The SE(3) logarithm of a planar motion is the SE(2)
logarithm padded with zeros, so the embedded problem has exactly the 2-D cost and optimum.

Reading is all-or-nothing and vectorised (the lines of each record type are parsed as one numpy
array): every line is validated first (field count, numbers, tags, quaternion norms, information,
known vertices), and a :class:`FormatError` names the file and line of the first problem of the
first failing check; the network is built only from a completely valid file.

Modules: :mod:`~ga_ros.io.g2o.records` (tags and field parsing), :mod:`~ga_ros.io.g2o.reader`,
:mod:`~ga_ros.io.g2o.writer`, :mod:`~ga_ros.io.g2o.graph` (:class:`PoseGraph`),
:mod:`~ga_ros.io.g2o.information` (information checks and covariances),
:mod:`~ga_ros.io.g2o.offsets` (sensor offsets), :mod:`~ga_ros.io.g2o.planar` (SE(2) in SE(3)),
:mod:`~ga_ros.io.g2o.cost` (:func:`graph_cost`).
"""

from ga_ros.io.g2o.cost import edge_errors, graph_cost
from ga_ros.io.g2o.graph import PoseGraph
from ga_ros.io.g2o.information import InformationRepairWarning
from ga_ros.io.g2o.planar import se2_to_se3, se3_to_se2
from ga_ros.io.g2o.reader import read_g2o
from ga_ros.io.g2o.writer import write_g2o

__all__ = ['InformationRepairWarning', 'PoseGraph', 'edge_errors', 'graph_cost', 'read_g2o',
           'se2_to_se3', 'se3_to_se2', 'write_g2o']
