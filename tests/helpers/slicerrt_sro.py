"""SlicerRT's reading of a DICOM Spatial Registration object, reimplemented with pydicom.

Source: SlicerRt/SlicerRT, ``DicomSroImportExport/Logic/vtkSlicerDicomSroReader.cxx``,
``vtkSlicerDicomSroReader::LoadSpatialRegistration`` (commit df6ef69c, lines 272-364):

* lines 276-283: ``invMatrix`` and ``forMatrix`` are both ``diag(-1, -1, 1, 1)``;
* lines 294-357: for every Registration Sequence item, every Matrix Registration Sequence item
  and every Matrix Sequence item that has a Frame of Reference Transformation Matrix Type, the
  16 values are read row-major (``SetElement(n / 4, n % 4, ...)``, line 347) and multiplied on
  the right: ``SpatialRegistrationMatrix = SpatialRegistrationMatrix @ M`` (lines 350-352),
  starting from the identity (line 193);
* lines 359-361 ("Change to RAS system from DICOM LPS system"): ``invMatrix @ S @ forMatrix``,
  the LPS->RAS flip on BOTH sides.

``vtkSlicerDicomSroImportExportModuleLogic::LoadSpatialRegistration`` (same repository,
``vtkSlicerDicomSroImportExportModuleLogic.cxx`` line 318) sets that matrix as the linear
transform node's ``MatrixTransformToParent``: a point placed under the node (its child, here a
robot-frame point) is shown at ``S_ras @ p`` in Slicer's RAS world.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from pydicom.dataset import Dataset

F64 = npt.NDArray[np.float64]
LPS_RAS_FLIP: F64 = np.diag([-1.0, -1.0, 1.0, 1.0])


def slicerrt_transform_to_parent(ds: Dataset) -> F64:
    """The ``MatrixTransformToParent`` SlicerRT gives the REG object ``ds`` (see the module docstring)."""
    s = np.eye(4)
    for item in ds.RegistrationSequence:
        for mreg in item.get("MatrixRegistrationSequence", []):
            for mat in mreg.get("MatrixSequence", []):
                if "FrameOfReferenceTransformationMatrixType" not in mat:
                    continue
                values = [float(v) for v in mat.FrameOfReferenceTransformationMatrix]
                s = s @ np.asarray(values, dtype=np.float64).reshape(4, 4)
    return LPS_RAS_FLIP @ s @ LPS_RAS_FLIP
