"""Fault catalogue: bad inputs, kills, full disks, damaged files, hostile peers and floods,
injected into LIVE alignment nodes started with their default settings (``ga-ros bench faults``).

Each case starts ``alignment_node`` as a process (own ``ROS_DOMAIN_ID``), feeds it a survey
(a small simulated one, or a measurements bag such as ``bags/aerial_measurements``) with the
fault injected, by a transient-local publisher or by ``ga-ros play``, ends the input with the
end-of-input message and compares the final published path with :class:`TrackWindowAligner`
fed the clean measurements. One :class:`Row` per case: the node survived (alive, or exited
cleanly where the fault stops it; no traceback in its log), what it counted, the nodes
expected and the nodes kept (within 1 mm of the reference), and the time to recover (restart
until the node holds again every node it held before the fault).

Nodes lost because a measurement never arrives at all (a gap) are not caught here: the
publishers keep their history, so a restarted node gets everything again.

One case runs on the alignment session in process instead (the ROS-free object the node
drives): the journal-only recovery of a survey with fixes, compared bit for bit.

The package: :mod:`.survey` (the data of a case: survey, context, row, reference paths),
:mod:`.harness` (a live node process and its client, ``ga-ros play``, tmpfs mounts), the cases
(:mod:`.input_cases`, :mod:`.crash_cases`, :mod:`.peer_cases`, :mod:`.state_cases` of the
default state and another survey, :mod:`.session_cases`) and :mod:`.catalogue` (the cases by
name, the run of one, the table).
"""

from ga_ros.ros.fault_catalogue.catalogue import catalogue, run_case, table
from ga_ros.ros.fault_catalogue.survey import Row, Survey, bag_survey

__all__ = ['Row', 'Survey', 'bag_survey', 'catalogue', 'run_case', 'table']
