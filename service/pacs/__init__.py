"""Archive of each accepted registration's Spatial Registration object to a PACS:
:mod:`service.pacs.scu` (one C-STORE, classified), :mod:`service.pacs.exporter` (the queue's worker)."""
