"""The FastAPI service, DICOM watcher, orchestration, persistence and the ``oarmreg`` CLI."""
