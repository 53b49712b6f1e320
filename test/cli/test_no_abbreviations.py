"""No argparse abbreviations anywhere: ``--map`` must not be taken as ``--map-frame``.

Every parser is walked: the ``ga-ros`` tree at run time (each subcommand), and every
``ArgumentParser(...)`` / ``add_parser(...)`` call in the sources (benchmarks, tools, nodes,
scripts), which must say ``allow_abbrev=False``.
"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest

from ga_ros.cli.main import build_parser, main

REPO = Path(__file__).resolve().parents[2]


def _parsers(parser: argparse.ArgumentParser, path: str = 'ga-ros'):
    yield path, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _parsers(sub, f'{path} {name}')


def test_every_ga_ros_parser_refuses_abbreviations():
    found = dict(_parsers(build_parser()))
    assert {'ga-ros', 'ga-ros replay', 'ga-ros demo', 'ga-ros bench'} <= set(found)
    loose = [path for path, p in found.items() if p.allow_abbrev]
    assert not loose, f'parsers accepting abbreviations: {loose}'


def _calls_without_flag(source: str):
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Call):
            continue
        fn = node.func
        name = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, 'id', '')
        if name not in ('ArgumentParser', 'add_parser'):
            continue
        flag = [k for k in node.keywords if k.arg == 'allow_abbrev']
        if not (flag and isinstance(flag[0].value, ast.Constant)
                and flag[0].value.value is False):
            yield node.lineno


def test_every_parser_in_the_sources_refuses_abbreviations():
    files = [f for d in ('ga_ros', 'scripts', 'launch') for f in sorted((REPO / d).rglob('*.py'))]
    assert len(files) > 50
    missing = [f'{f.relative_to(REPO)}:{line}' for f in files
               for line in _calls_without_flag(f.read_text())]
    assert not missing, f'ArgumentParser / add_parser without allow_abbrev=False: {missing}'


def test_the_flag_finder_sees_a_parser_without_the_flag():
    """The source scan can fail: it flags a parser that allows abbreviations."""
    assert list(_calls_without_flag('import argparse\np = argparse.ArgumentParser(prog="x")\n'))
    assert not list(_calls_without_flag('p = argparse.ArgumentParser(allow_abbrev=False)\n'))


def test_map_is_not_taken_as_map_frame(tmp_path, capsys):
    """``--map`` is the maps' switch: ``--map world`` must not become ``--map-frame world``."""
    with pytest.raises(SystemExit) as exc:
        main(['replay', str(tmp_path), '--map', 'world', '--info'])
    assert exc.value.code == 2
    assert 'unrecognized arguments: world' in capsys.readouterr().err
