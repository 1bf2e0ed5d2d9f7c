"""One module per ``oarmreg`` subcommand.

Each module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``.  Keep module-level imports light: heavy imports go
inside ``run`` so ``oarmreg --help`` stays fast.

Enters: the parsed argv of one subcommand and the TOML it names.
Leaves: its output on stdout and in the files named, and the exit code (:mod:`service.error_map`).
"""
