"""Shipped in the wheel as the package ``oarmreg_configs`` (see ``pyproject.toml``).

Read through :mod:`registration.io.resources`; edit the TOML and URDF files beside this one.
"""
