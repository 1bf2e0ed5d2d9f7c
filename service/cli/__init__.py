"""The ``oarmreg`` command line: one module per command under ``commands/``.

Enters: argv, the TOML settings, files named on the command line.
Leaves: text and JSON on stdout, files the user named, and a documented exit code.
"""
