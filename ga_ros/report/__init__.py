"""The reproduction of the paper's experiments: ``ga-ros reproduce`` (Markdown + PNG + JSON)."""

from ga_ros.report.config import ReproduceConfig, preset
from ga_ros.report.writer import run_reproduction

__all__ = ['ReproduceConfig', 'preset', 'run_reproduction']
