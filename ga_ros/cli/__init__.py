"""The ``ga-ros`` command line: one module per subcommand in :mod:`ga_ros.cli.commands`."""
