"""The Canny + probabilistic Hough baseline (the acstools ``satdet`` approach), for comparison.

acstools ``satdet`` (Borncamp & Lim, HST ACS/WFC) rescales the image between two percentiles,
finds edges with Canny, removes small edge groups, and runs skimage's probabilistic Hough
transform; a trail is a group of segments at a common angle. Its defaults are kept here.
"""
import numpy as np

from inject.masking.geometry import Line, angle_difference

#: acstools ``satdet`` defaults.
SATDET = {"sigma": 2.0, "low_thresh": 0.1, "h_thresh": 0.5, "small_edge": 60,
          "line_len": 200, "line_gap": 75, "percentile": (4.5, 93.0), "threshold": 210}


def canny_hough(image, seed=1, **options):
    """Line segments found by Canny edges and the probabilistic Hough transform.

    Parameters
    ----------
    image : array_like
        2-D image.
    seed : int
        Seed of the probabilistic Hough transform (it samples edge pixels at random).
    **options
        Overrides of :data:`SATDET`.

    Returns
    -------
    list of Line
        One per segment (endpoints in pixels).
    """
    from skimage.exposure import rescale_intensity
    from skimage.feature import canny
    from skimage.morphology import remove_small_objects
    from skimage.transform import probabilistic_hough_line

    o = SATDET | options
    img = np.asarray(image, dtype=np.float64)
    img = np.where(np.isfinite(img), img, np.nanmedian(img))
    p1, p2 = np.percentile(img, o["percentile"])
    img = rescale_intensity(img, in_range=(max(p1, 0.0), p2))
    top = img.max()
    edges = canny(img, sigma=o["sigma"], low_threshold=top * o["low_thresh"],
                  high_threshold=top * o["h_thresh"])
    # satdet removes edge groups smaller than small_edge pixels (8-connected); skimage 0.26
    # renamed min_size (strictly smaller) to max_size (smaller or equal).
    edges = remove_small_objects(edges, max_size=o["small_edge"] - 1, connectivity=2)
    theta = np.radians(np.arange(2, 178, 0.5))  # satdet skips 0 and 90 +- 2 deg (bad columns)
    segments = probabilistic_hough_line(edges, threshold=o["threshold"],
                                        line_length=o["line_len"], line_gap=o["line_gap"],
                                        theta=theta, rng=seed)
    return [Line(float(x0), float(y0), float(x1), float(y1)) for (x0, y0), (x1, y1) in segments]


def segments_match(segments, true_line, max_angle_deg=1.0, max_offset_px=10.0):
    """Indices of segments along ``true_line`` (angle within ``max_angle_deg``, both ends
    within ``max_offset_px`` of it)."""
    out = []
    for i, seg in enumerate(segments):
        if angle_difference(seg.angle_deg, true_line.angle_deg) > max_angle_deg:
            continue
        _, d = true_line.coordinates([seg.x0, seg.x1], [seg.y0, seg.y1])
        if np.all(np.abs(d) <= max_offset_px):
            out.append(i)
    return out
