"""The pixel pass: decode every frame with pydicom's public decoder API into one preallocated HU array.

Each frame is decoded by :meth:`pydicom.pixels.decoders.base.Decoder.as_array` from the file,
positioned at the Pixel Data value the header pass found (so no header is parsed twice); compressed
transfer syntaxes go through pydicom's plugins (pylibjpeg included).  Then the Modality LUT rescale
(PS3.3 C.11.1.1.2, as :func:`pydicom.pixels.apply_rescale`)
``HU = RescaleSlope (0028,1053) · stored + RescaleIntercept (0028,1052)`` is applied straight into
the output slice: in int32 with a range check when the rescale is integral (int16 output), else in
float32.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydicom.uid import UID

from registration.dicom.errors import PixelDataError, SeriesError, VolumeTooLargeError
from registration.dicom.files import open_regular
from registration.dicom.headers import SliceHeader, slice_name

log = logging.getLogger(__name__)


def output_dtype(slices: Sequence[SliceHeader]) -> type[np.int16] | type[np.float32]:
    """int16 when every slice's rescale is integral (values are range-checked while reading), else float32."""
    integral = all(float(h.slope).is_integer() and float(h.intercept).is_integer() for h in slices)
    return np.int16 if integral else np.float32


def read_voxels(slices: Sequence[SliceHeader], series_uid: str) -> NDArray[Any]:
    """Fill one preallocated (n, rows, columns) array slice by slice, rescaled to HU."""
    n, rows, columns = len(slices), slices[0].rows, slices[0].columns
    try:
        out: NDArray[Any] = np.empty((n, rows, columns), dtype=output_dtype(slices))
    except MemoryError as exc:  # below MAX_VOLUME_BYTES but more than this machine has left
        raise VolumeTooLargeError(
            f"series {series_uid}: not enough memory for {n} slices of {rows} x {columns} pixels "
            f"({type(exc).__name__}: {exc}). Close other programs or load the series on a machine with "
            "more memory.",
            files=[slices[0].path],
            series_uid=series_uid,
        ) from exc
    for k, h in enumerate(slices):
        try:
            raw = decode_frame(h)
        except SeriesError:
            raise
        except MemoryError as exc:  # a damaged header asked the decoder for more than is left
            raise VolumeTooLargeError(
                f"series {series_uid}: decoding {slice_name(h)} ran out of memory ({exc}); its Rows / "
                "Columns / BitsAllocated are probably damaged. Re-export the series.",
                files=[h.path],
                series_uid=series_uid,
            ) from exc
        except Exception as exc:
            raise PixelDataError(
                f"series {series_uid}: cannot read the pixel data of {slice_name(h)} (transfer syntax "
                f"{UID(h.transfer_syntax_uid).name}; {type(exc).__name__}: {exc}). The file is damaged or "
                "needs a decoder plugin that is not installed (pylibjpeg, pylibjpeg-libjpeg, "
                "pylibjpeg-openjpeg); re-export uncompressed or install the plugin.",
                files=[h.path],
                series_uid=series_uid,
            ) from exc
        if out.dtype == np.int16 and not _rescale_int16(raw, h, out[k], series_uid):
            out = out.astype(np.float32)  # rare: one extra copy while converting
        if out.dtype == np.float32:
            np.multiply(raw, h.slope, out=out[k], casting="unsafe")
            out[k] += np.float32(h.intercept)
    return out


def _rescale_int16(raw: NDArray[Any], h: SliceHeader, target: NDArray[Any], series_uid: str) -> bool:
    """Write ``slope · raw + intercept`` into int16 ``target``; False (nothing written) if out of range."""
    slope, intercept = int(h.slope), int(h.intercept)
    if slope == 1 and intercept == 0 and raw.dtype == np.int16:  # stored values are HU already
        np.copyto(target, raw)
        return True
    ends = (int(raw.min()) * slope + intercept, int(raw.max()) * slope + intercept)
    lo, hi = min(ends), max(ends)
    if lo < -32768 or hi > 32767:
        log.info(
            "series %s: %s has HU %d..%d outside int16; switching the volume to float32",
            series_uid,
            slice_name(h),
            lo,
            hi,
        )
        return False
    stored = raw if slope == 1 else raw.astype(np.int32) * slope  # in range: int32, stored without overflow
    np.add(stored, np.int32(intercept), out=target, casting="unsafe")
    return True


def decode_frame(h: SliceHeader) -> NDArray[Any]:
    """Stored values of one frame, shape (rows, columns), unused high bits corrected as pydicom does.

    Raises
    ------
    PixelDataError
        The decoded frame is not a single (rows, columns) plane.
    """
    from pydicom.pixels.decoders.base import get_decoder  # = pydicom.pixels.get_decoder, typed

    decoder = get_decoder(UID(h.transfer_syntax_uid))
    opts: dict[str, Any] = {  # the decoding options a non-Dataset source needs (pydicom decoder docs)
        "rows": h.rows,
        "columns": h.columns,
        "samples_per_pixel": h.samples_per_pixel,
        "photometric_interpretation": h.photometric or "MONOCHROME2",
        "number_of_frames": h.n_frames,
        "bits_allocated": h.bits_allocated,
        "bits_stored": h.bits_stored,
        "pixel_representation": h.pixel_representation,
        "pixel_keyword": "PixelData",
        "pixel_vr": h.pixel_vr or ("OW" if h.bits_allocated > 8 else "OB"),
        "transfer_syntax_uid": UID(h.transfer_syntax_uid),
        "view_only": True,  # native data: no writeable copy, the frame is copied into the volume anyway
    }
    with open_regular(h.path) as f:
        f.seek(h.pixel_offset)  # the decoder reads from a file positioned at the Pixel Data value
        arr, _ = decoder.as_array(f, index=h.frame, validate=True, **opts)
    if arr.shape != (h.rows, h.columns):
        raise PixelDataError(
            f"{slice_name(h)}: decoded pixel data has shape {arr.shape}, expected ({h.rows}, {h.columns}). "
            "The file is not a single-plane greyscale CT image; remove it or re-export the series.",
            files=[h.path],
            series_uid=h.series_uid,
        )
    return _fix_high_bits(arr, h.bits_stored)


def _fix_high_bits(arr: NDArray[Any], bits_stored: int) -> NDArray[Any]:
    """Clear (unsigned) or sign-extend (signed) the bits above BitsStored (0028,0101); idempotent."""
    width = arr.dtype.itemsize * 8
    shift = width - bits_stored
    if 0 < shift < width and arr.dtype.kind in "iu":
        if not arr.flags.writeable:
            arr = arr.copy()
        np.left_shift(arr, shift, out=arr)
        np.right_shift(arr, shift, out=arr)
    return arr
