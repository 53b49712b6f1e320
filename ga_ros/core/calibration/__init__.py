"""Self-calibration: systematic errors of the sources as additional parameters of the
adjustment, estimated where the network determines them (:mod:`.parameters`: what each
parameter corrects; :mod:`.batch`: the batch adjustment with them and their tests)."""

from ga_ros.core.calibration.batch import (
    AdditionalParameter,
    CalibrationConfig,
    CalibrationReport,
    NoiseFactor,
    solve_with_calibration,
)
from ga_ros.core.calibration.parameters import (
    PARAMETERS,
    ScaleCorrection,
    YawRateCorrection,
    corrected_motions,
    misclosure_jacobian,
)

__all__ = ['PARAMETERS', 'AdditionalParameter', 'CalibrationConfig', 'CalibrationReport',
           'NoiseFactor', 'ScaleCorrection', 'YawRateCorrection', 'corrected_motions',
           'misclosure_jacobian', 'solve_with_calibration']
