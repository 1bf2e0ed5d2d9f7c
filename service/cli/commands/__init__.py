"""One module per ``oarmreg`` subcommand.

Each module defines ``HELP`` (one line), ``add_arguments(parser)`` and
``run(args) -> int``.  Keep module-level imports light: heavy imports go
inside ``run`` so ``oarmreg --help`` stays fast.
"""
