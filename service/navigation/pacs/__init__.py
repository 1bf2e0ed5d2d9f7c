"""Archive of each accepted registration's Spatial Registration object to a PACS:
:mod:`service.navigation.pacs.scu` (one C-STORE, classified), :mod:`service.navigation.pacs.exporter` (the
queue's worker)."""
