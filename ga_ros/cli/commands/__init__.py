"""Subcommands of ``ga-ros``; each module defines ``register(subparsers)`` (see ``main.py``)."""
