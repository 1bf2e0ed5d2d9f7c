"""Stage 2 of the flow: a loaded series as the detector needs it.

After :mod:`registration.dicom` has turned files into a :class:`~registration.imaging.volume.Volume`
(voxels and ``image_from_voxel``), this stage holds the volume record itself, the polar metal
artifact reduction of Bai et al. 2018 §2.1 (:mod:`.mar`), the moment-invariant circles in a slice
(:mod:`.circles`, §2.2), and the scan's geometry as the calibration planner needs it
(:mod:`.scan_geometry`).  Next: :mod:`registration.detection`.
"""
