"""The way in: O-arm series arrive (folder watcher, DICOM C-STORE SCP), are accumulated into whole
series, checked, recorded with the robot's joint snapshot and their volume cached.

Enters: files in the watched folder, C-STORE associations from the O-arm.
Leaves: scan records in the store and ``ScanArrived`` / ``ScanInvalid`` / ``ScanWithdrawn`` events
on the bus (:mod:`service.events`).
"""
