"""The alignment session: one ROS-free object that the alignment node and the replay both drive.

It owns the :class:`~ga_ros.core.window.TrackWindowAligner`, the gap healer
(:class:`~ga_ros.core.gaps.GapHealer`: measurements whose source node is unknown are held, read
backwards or bridged instead of rejected), the rejection counters (keyed by the typed
:class:`~ga_ros.errors.Reason` of each rejection), the crash insurance (measurement journal +
snapshots, :mod:`ga_ros.pipeline.journal`; held measurements and bridges are journaled too) and
the diagnostic values. One call per measurement: :meth:`AlignmentSession.step`
``(measurement) -> StepOutput``. The node turns messages into measurements and
:class:`StepOutput` into messages; nothing else.

The package: :mod:`.facade` (:class:`AlignmentSession`), :mod:`.config` (:class:`SessionConfig`),
:mod:`.outputs` (:class:`StepOutput`, :class:`Health`, the counters), :mod:`.rejections` (typed
reasons), :mod:`.restore` (the gap healer of a recovered state), :mod:`.survey_identity` (the
same survey or another one after a restart) and :mod:`.diagnostics`.
"""

from ga_ros.pipeline.session.config import SessionConfig
from ga_ros.pipeline.session.facade import AlignmentSession
from ga_ros.pipeline.session.outputs import MAX_ERROR_CHARS, Health, StepOutput, Warn, bounded

__all__ = ['MAX_ERROR_CHARS', 'AlignmentSession', 'Health', 'SessionConfig', 'StepOutput', 'Warn',
           'bounded']
