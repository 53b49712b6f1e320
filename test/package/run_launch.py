"""Run a package's launch file with ROS's own launch system, as ``ros2 launch`` does.

    python run_launch.py PACKAGE FILE [name:=value ...]

The file is looked up in the package's installed share folder (``share/PACKAGE/launch/FILE``,
through the ament index of the sourced workspace) and run by ``launch.LaunchService`` with the
arguments, as the ``ros2 launch`` verb (ros2launch, which needs the ros2cli) does. SIGINT shuts
the launch down (its processes get SIGINT, then SIGTERM); the exit code is the launch
service's.
"""

from __future__ import annotations

import signal
import sys
from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch.actions import IncludeLaunchDescription
from launch.launch_description_sources import AnyLaunchDescriptionSource

from launch import LaunchDescription, LaunchService


def main(argv: list[str]) -> int:
    package, name, *arguments = argv
    # ros2 launch typed in a terminal starts with Python's SIGINT handler. A process started
    # in the background of a non-interactive shell (`cmd &`, nohup, some CI runners)
    # inherits SIGINT ignored, Python then installs no handler, and launch, which only
    # watches signal.set_wakeup_fd, never sees the Ctrl-C: give it the terminal's handler
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    path = Path(get_package_share_directory(package)) / 'launch' / name
    if not path.is_file():
        print(f'no launch file {name} in {path.parent}', file=sys.stderr)
        return 2
    pairs = [tuple(a.split(':=', 1)) for a in arguments]
    service = LaunchService(argv=arguments, noninteractive=True)
    service.include_launch_description(LaunchDescription([IncludeLaunchDescription(
        AnyLaunchDescriptionSource(str(path)), launch_arguments=pairs)]))
    return service.run()


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
