"""Archive of each accepted registration's Spatial Registration object to a PACS:
:mod:`service.navigation.pacs.scu` (one C-STORE, classified), :mod:`service.navigation.pacs.exporter` (the
queue's worker).

Enters: accepted registrations (``RegistrationDone``) and retry requests.
Leaves: REG objects by C-STORE to the PACS; the export queue's rows and events.
"""
