"""Self-calibration: systematic errors of the sources as additional parameters of the
adjustment, estimated where the network determines them (:mod:`.parameters`: what each
odometry parameter corrects; :mod:`.camera_parameters`: a camera extrinsic's rotation;
:mod:`.fix_parameters`: what each fix-source parameter corrects; :mod:`.models`: a
parameter as a constant, a random walk, or a constant with a random walk about it;
:mod:`.batch`: the batch adjustment with them and their tests)."""

from ga_ros.core.calibration.batch import (
    AdditionalParameter,
    CalibrationConfig,
    CalibrationReport,
    NoiseFactor,
    WalkEstimate,
    solve_with_calibration,
)
from ga_ros.core.calibration.camera_parameters import (
    CAMERA_PARAMETERS,
    ExtrinsicRotationAxis,
    camera_sources,
    check_cameras,
)
from ga_ros.core.calibration.fix_parameters import (
    FIX_PARAMETERS,
    FixObservations,
    FixOffsetAxis,
    TimeOffset,
    book_observations,
    fix_priors,
    node_velocities,
)
from ga_ros.core.calibration.models import (
    MODELS,
    BiasWalk,
    ConstantLevel,
    ParameterModel,
    RandomWalk,
    parameter_model,
)
from ga_ros.core.calibration.parameters import (
    PARAMETERS,
    ScaleCorrection,
    YawRateCorrection,
    corrected_motions,
    misclosure_jacobian,
)

__all__ = ['CAMERA_PARAMETERS', 'FIX_PARAMETERS', 'MODELS', 'PARAMETERS', 'AdditionalParameter',
           'BiasWalk', 'CalibrationConfig', 'CalibrationReport', 'ConstantLevel',
           'ExtrinsicRotationAxis',
           'FixObservations', 'FixOffsetAxis', 'NoiseFactor', 'ParameterModel', 'RandomWalk',
           'ScaleCorrection', 'TimeOffset', 'WalkEstimate', 'YawRateCorrection',
           'book_observations', 'camera_sources', 'check_cameras', 'corrected_motions',
           'fix_priors', 'misclosure_jacobian', 'node_velocities', 'parameter_model',
           'solve_with_calibration']
