"""``ga-ros`` entry point.

Each module in :mod:`ga_ros.cli.commands` defines ``register(subparsers) -> None``, which adds one
subcommand whose parser has ``set_defaults(func=run)`` with ``run(args) -> int``; the command
``foo-bar`` lives in module ``foo_bar``, so a command line that names one imports only that module
(start-up of ``ga-ros solve`` is not paid for the ROS replay stack), and ``ga-ros --help``
lists the commands from :data:`ga_ros.cli.commands.SUMMARIES` without importing any of them
(nor NumPy). Errors derived from :class:`ga_ros.errors.GaError` become a one-line message and
exit code 1.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import sys

from ga_ros import __version__
from ga_ros.cli import commands
from ga_ros.errors import GaError, UsageError

#: The options that print a command's help and exit (no BLAS library to load for them).
HELP = frozenset(('-h', '--help'))


def command_modules() -> list[str]:
    """Names of the modules of :mod:`ga_ros.cli.commands` (one subcommand each)."""
    import pkgutil  # only when listing every command (start-up of a named command)

    return sorted(m.name for m in pkgutil.iter_modules(commands.__path__))


def command_module(command: str | None) -> str | None:
    """The module of :mod:`ga_ros.cli.commands` that holds ``command`` (``None``: no such
    command, or no command given), found without importing it."""
    name = '' if command is None else command.replace('-', '_')
    if (name.isidentifier() and not name.startswith('_')
            and importlib.util.find_spec(f'{commands.__name__}.{name}') is not None):
        return name
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``ga-ros`` parser with ``command`` in full when it names one; otherwise every command
    listed with its summary (:data:`~ga_ros.cli.commands.SUMMARIES`), none imported (a module
    without a summary is imported and registers itself)."""
    parser = argparse.ArgumentParser(
        prog='ga-ros',
        description='Global alignment of sensor trajectories from noisy motion measurements.',
        allow_abbrev=False)
    parser.add_argument('--version', action='version', version=f'ga-ros {__version__}')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    name = command_module(command)
    for module_name in [name] if name else command_modules():
        summary = commands.SUMMARIES.get(module_name.replace('_', '-'))
        if name is None and summary is not None:  # listed only: ``ga-ros --help``, a typo
            sub.add_parser(module_name.replace('_', '-'), help=summary, add_help=False,
                           allow_abbrev=False)
            continue
        module = importlib.import_module(f'{commands.__name__}.{module_name}')
        if hasattr(module, 'register'):
            module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    named = command_module(argv[0] if argv else None) is not None
    if named and not HELP.intersection(argv):  # a command runs (not only its --help): limit BLAS
        from ga_ros.runtime import fewer_collections, limit_blas_threads, openblas_threads_at_load

        fewer_collections()  # before the imports: ~4 % of a small solve's CPU
        with openblas_threads_at_load():  # each library loads with the limit's threads
            _blas = limit_blas_threads()  # noqa: F841 (loads NumPy's, SciPy's, CHOLMOD's BLAS;
            # kept alive for the whole command)
    elif named:  # a command's help: its parser may import SciPy (ga_ros.runtime is light)
        from ga_ros.runtime import scipy_imports_trimmed

        scipy_imports_trimmed()
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
