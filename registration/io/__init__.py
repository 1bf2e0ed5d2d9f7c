"""What the registration writes and reads besides DICOM images: points files, the DICOM
Spatial Registration object, and the shipped resources (phantoms, robot models, settings).

:mod:`.points` (the ``oarmreg`` JSON / CSV point files), :mod:`.sro` (the registration as a DICOM
Spatial Registration object, docs/or-integration.md), :mod:`.resources` (``configs/`` as the
package ``oarmreg_configs`` through importlib.resources).
"""
