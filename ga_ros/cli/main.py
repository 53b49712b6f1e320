"""``ga-ros`` entry point.

Each module in :mod:`ga_ros.cli.commands` defines ``register(subparsers) -> None``, which adds one
subcommand whose parser has ``set_defaults(func=run)`` with ``run(args) -> int``; the command
``foo-bar`` lives in module ``foo_bar``, so a command line that names one imports only that module
(start-up of ``ga-ros solve`` is not paid for the ROS replay stack). Errors derived from
:class:`ga_ros.errors.GaError` become a one-line message and exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from ga_ros import __version__
from ga_ros.cli import commands
from ga_ros.errors import GaError, UsageError
from ga_ros.runtime import limit_blas_threads


def command_modules() -> list[str]:
    """Names of the modules of :mod:`ga_ros.cli.commands` (one subcommand each)."""
    import pkgutil  # only when listing every command (start-up of a named command)

    return sorted(m.name for m in pkgutil.iter_modules(commands.__path__))


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``ga-ros`` parser with every subcommand, or only ``command`` when it names one."""
    parser = argparse.ArgumentParser(
        prog='ga-ros',
        description='Global alignment of sensor trajectories from noisy motion measurements.',
        allow_abbrev=False)
    parser.add_argument('--version', action='version', version=f'ga-ros {__version__}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    name = '' if command is None else command.replace('-', '_')
    if (name.isidentifier() and not name.startswith('_')
            and importlib.util.find_spec(f'{commands.__name__}.{name}') is not None):
        names = [name]  # the command named: no listing of the package (pkgutil)
    else:
        names = command_modules()
    for name in names:
        module = importlib.import_module(f'{commands.__name__}.{name}')
        if hasattr(module, 'register'):
            module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    _blas = limit_blas_threads()  # noqa: F841 (kept alive for the whole command)
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(argv[0] if argv else None)
    args = parser.parse_args(argv)
    if not getattr(args, 'func', None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except GaError as exc:
        print(f'ga-ros {args.command}: error: {exc}', file=sys.stderr)
        return 2 if isinstance(exc, UsageError) else 1
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
