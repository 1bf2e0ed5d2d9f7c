"""The FastAPI service, DICOM watcher, orchestration, persistence and the ``oarmreg`` CLI.

Enters: what the O-arm sends (DICOM files, C-STORE), the robot's joint angles (drivers/), API calls and
the command line.
Leaves: the registration (REST, OpenIGTLink, the REG object), its records in SQLite, the page.
"""
