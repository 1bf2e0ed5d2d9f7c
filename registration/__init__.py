"""Pure computation for O-arm ↔ Stäubli spatial registration, in the order the data flows.

1. :mod:`registration.dicom`: files → a :class:`~registration.imaging.volume.Volume` (series
   selection, safe open, headers, pixels; the one place this package reads files);
2. :mod:`registration.imaging`: the volume record, polar metal artifact reduction, the
   moment-invariant circles, the scan's geometry;
3. :mod:`registration.detection`: volume → sphere centres in the image frame, and why not;
4. :mod:`registration.matching`: robot points ↔ image points → ``image_from_robot``, its quality
   figures and its refusals, and verification against a later scan.

Beside the flow: :mod:`registration.model` (frames, the phantom and its symmetry, the robot's
kinematics, stillness), used by every stage; :mod:`registration.calibration` (many registrations →
a calibrated robot model, the pose planner, the URDF); :mod:`registration.io` (points files, the
DICOM Spatial Registration object, the shipped resources).  :mod:`registration.pipeline` runs
stages 1–4; :mod:`registration.errors` is the error hierarchy.

No sockets, threads, watchers or logging configuration live here: arrays and frozen dataclasses
in, arrays and dataclasses out (docs/design.md §2).
"""

__version__ = "0.1.0"
