"""The ``ga-ros`` subcommands: the command ``foo-bar`` lives in module ``foo_bar``.

:data:`SUMMARIES` is each command's one-line help, the one definition that both the module's
parser and ``ga-ros --help`` show: the listing needs no command's module (start-up: the
modules import the solver, the replay stack, ROS message types).
"""

from __future__ import annotations

#: ``ga-ros COMMAND``: its one-line help.
SUMMARIES: dict[str, str] = {
    'bench': 'run a benchmark and print its figures',
    'demo': 'run the pipeline end to end on the bundled sample bags',
    'make-bags': 'regenerate the sample bags (aerial measurements, stereo images)',
    'play': 'publish a bag live (with /clock) into a running ROS 2 graph',
    'replay': 'replay a recording (rosbag2, ROS 1 .bag, EuRoC or KITTI folder) offline '
              'through the alignment pipeline',
    'reproduce': "run the paper's experiments and write a report",
    'simulate': "simulate one of the paper's surveys with ground truth",
    'solve': 'optimise a g2o pose graph (batch, or track by track)',
}
