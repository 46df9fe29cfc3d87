"""Independent peers the measuring code is compared with (tests and ``bench/bench_extract.py``)."""

import cv2
import numpy as np

from fieldcal.measure.coded import to_uint8
from fieldcal.measure.imageio import check_image


def opencv_blob_centres(image, *, polarity: str = "dark") -> np.ndarray:
    """Centres (n, 2) [px] found by ``cv2.SimpleBlobDetector`` with its default settings.

    The peer that :func:`fieldcal.measure.discs.detect_targets` is compared with. A 16-bit
    image is first stretched to 8 bits (:func:`fieldcal.measure.coded.to_uint8`), which the
    detector needs; ``blobColor`` follows ``polarity``, every other setting is OpenCV's
    default. OpenCV's keypoints use the same pixel convention as CONTRACT section 1.
    """
    if polarity not in ("dark", "bright"):
        raise ValueError(f"polarity must be 'dark' or 'bright', got {polarity!r}")
    img8 = to_uint8(check_image(image))
    params = cv2.SimpleBlobDetector_Params()
    params.blobColor = 0 if polarity == "dark" else 255
    det = cv2.SimpleBlobDetector_create(params)
    kps = det.detect(img8)
    return np.array([k.pt for k in kps], float).reshape(-1, 2)
