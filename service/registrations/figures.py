"""Pipeline results → the figures stored with a registration or a verification."""

from __future__ import annotations

import numpy as np

from registration import __version__
from registration.matching.verification import VerificationResult
from registration.model.phantom import Phantom
from registration.pipeline import ScanRegistration, SpherePair
from service.records import (
    DetectionSummary,
    JointSnapshot,
    JSONDict,
    RegistrationFigures,
    ScanRecord,
    SphereError,
    SphereMatch,
    VerificationFigures,
    points3,
)


def sphere_id(phantom: Phantom, robot_index: int) -> str:
    """The phantom hole id of the ``robot_index``-th filled hole (the index itself if out of range)."""
    ids = phantom.filled_ids
    return str(ids[robot_index]) if 0 <= robot_index < len(ids) else str(robot_index)


def registration_figures(
    run: ScanRegistration,
    phantom: Phantom,
    *,
    targets_source: str,
    provenance: JSONDict,
    load_s: float,
    predicted_chain_error_mm: float | None = None,
    chain_error_source: str = "",
    series_geometry: JSONDict | None = None,
) -> RegistrationFigures:
    """The figures of an accepted registration; ``provenance`` is stored as given."""
    res = run.result
    det = run.spheres.detection
    spheres = tuple(
        SphereMatch(
            sphere=sphere_id(phantom, int(ri)), robot_index=int(ri), image_index=int(ii), residual_mm=float(r)
        )
        for ri, ii, r in zip(res.robot_indices, res.image_indices, res.residuals_mm, strict=False)
    )
    timings: dict[str, float] = {"load_s": load_s, **run.timings_s}
    timings.update({f"register.{k}": float(v) for k, v in dict(res.timings_s).items()})
    return RegistrationFigures(
        fle_mm=float(res.fle_mm),
        n_expected=int(res.n_expected),
        n_detected=int(res.n_detected),
        n_matched=int(res.n_matched),
        symmetry_margin=int(res.symmetry_margin),
        rotation_det=float(res.rotation_det),
        predicted_tre_mm=tuple(float(v) for v in run.predicted_tre_mm),
        targets_image_mm=points3(run.targets_image_mm.tolist()),
        targets_source=targets_source,
        spheres=spheres,
        detection=DetectionSummary(
            method=str(det.method), n_rejected=len(det.rejections), timings_s=dict(det.timings_s or {})
        ),
        provenance=provenance,
        timings_s=timings,
        predicted_chain_error_mm=predicted_chain_error_mm,
        chain_error_source=chain_error_source,
        series_geometry=series_geometry,
        face_offset_mm=res.face_offset_mm,
        face_offset_se_mm=res.face_offset_se_mm,
    )


def provenance(
    scan: ScanRecord,
    snap: JointSnapshot,
    *,
    robot_model: str,
    tool0_from_phantom: np.ndarray,
    phantom: Phantom,
    config_hash: str,
) -> JSONDict:
    """Where a registration came from: the scan, the joints and the configuration."""
    return {
        "series_uid": scan.series_uid,
        "frame_of_reference_uid": scan.frame_of_reference_uid,
        "scan_folder": scan.folder,
        "joints_rad": None if snap.joints_rad is None else list(snap.joints_rad),
        "joints_received_at": snap.joints_received_at,
        "robot_link": snap.link_url,
        "robot_model": robot_model,
        "tool0_from_phantom": tool0_from_phantom.tolist(),
        "phantom": str(phantom.name),
        "config_hash": config_hash,
        "software_version": __version__,
    }


def verification_figures(
    spheres: SpherePair,
    res: VerificationResult,
    phantom: Phantom,
    *,
    gate_mm: float,
    snap: JointSnapshot,
) -> VerificationFigures:
    errors = tuple(
        SphereError(sphere=sphere_id(phantom, int(ri)), robot_index=int(ri), error_mm=float(e))
        for ri, e in zip(res.robot_indices, res.errors_mm, strict=False)
    )
    return VerificationFigures(
        errors=errors,
        n_expected=len(spheres.robot_mm),
        n_detected=len(spheres.image_mm),
        n_matched=len(errors),
        max_verification_error_mm=gate_mm,
        joints_rad=snap.joints_rad,
        joints_received_at=snap.joints_received_at,
    )
