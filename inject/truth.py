"""The TRUTH table: one row per streak, describing the streak as rendered on that image.

Every command that writes a TRUTH table (``simulate``, ``focalplane``, ``add-streak``) writes
these columns, in this order and with these types, whether the table has rows or not, so the
tables of an exposure stack.

The rule for what a row describes: the part of the track that the image receives, i.e. the
track clipped to the image grown by the profile's reach (``x0, y0`` where it enters, ``x1, y1``
where it leaves, ``length_px`` between them along the track). A track whose streak model
varies along it (a polyline, an orbit's pass) is described by the values at the middle of that
part (along the track), and ``flux_per_px_min_e``/``flux_per_px_max_e`` give the range of the
charge per pixel of track over it; for a straight track of one model the three are equal.
``charge_in_image_e`` is the charge the image received.

A row's ends describe a bent track (a polyline, an orbit's pass) only by its chord: the
vertices of the same part (:func:`vertices`) are the ``TRUTH_VERTICES`` table, one record per
vertex (:data:`VERTEX_COLUMNS`), from where the part enters to where it leaves, the track's
vertices in between; the renderer sweeps straight pieces between a track's vertices, so the
piecewise-linear path through them is the streak's ridge (where the profile rounds a sharp
corner, points of the rounded ridge stand for its vertex). A straight track has two: its
row's ends.
"""
import math

#: Column -> (numpy dtype, unit, description), in table order.
TRUTH_COLUMNS = {
    "satellite": ("i4", "", "index of the satellite in the scene"),
    "x0": ("f8", "pix", "where the streak enters the image (grown by the profile's reach), x"),
    "y0": ("f8", "pix", "where the streak enters, y"),
    "x1": ("f8", "pix", "where the streak leaves, x"),
    "y1": ("f8", "pix", "where the streak leaves, y"),
    "angle_deg": ("f8", "deg", "direction of the track at the middle, from +x"),
    "length_px": ("f8", "pix", "length of the part described, along the track"),
    "height_km": ("f8", "km", "orbit height at the middle"),
    "zenith_deg": ("f8", "deg", "zenith angle at the middle"),
    "phi_deg": ("f8", "deg", "angle of motion to the line of sight's plane, at the middle"),
    "range_km": ("f8", "km", "distance to the satellite at the middle"),
    "nadir_angle_deg": ("f8", "deg", "nadir angle at the middle"),
    "angular_speed_rad_s": ("f8", "rad/s", "angular speed across the star field, at the middle"),
    "t_eff_s": ("f8", "s", "effective exposure of a pixel, at the middle"),
    "apparent_mag": ("f8", "mag", "apparent AB magnitude at the middle"),
    "flux_per_px_e": ("f8", "electron", "charge per pixel of track at the middle"),
    "flux_per_px_min_e": ("f8", "electron", "least charge per pixel of track over the part"),
    "flux_per_px_max_e": ("f8", "electron", "most charge per pixel of track over the part"),
    "fwhm_arcsec": ("f8", "arcsec", "FWHM of the streak's cross-section at the middle"),
    "peak_e_per_px": ("f8", "electron", "most charge a pixel can get, at the middle"),
    "pixel_scale_arcsec": ("f8", "arcsec", "plate scale used along the track"),
    "field_angle_deg": ("f8", "deg", "traced pupil: angle from the optical axis at the middle "
                                     "(NaN with the annulus)"),
    "field_position_angle_deg": ("f8", "deg", "traced pupil: outward field radius from the "
                                              "direction of motion (NaN with the annulus)"),
    "sed_temperature_k": ("f8", "K", "traced pupil: the satellite's spectrum as a blackbody "
                                     "(NaN with the annulus)"),
    "charge_in_image_e": ("f8", "electron", "charge the image received from this streak"),
    "n_vertices": ("i4", "", "vertices of the track (2 for a straight track)"),
    "flags": ("i4", "", "TRUTH flag bits (FLAG_* header cards)"),
}


def _default(dtype):
    return -1 if dtype.startswith("i") else math.nan


def complete(rows):
    """The rows with every column of :data:`TRUTH_COLUMNS`, in order (a column a row lacks gets
    -1 for integers, NaN for floats; keys outside the table are dropped)."""
    return [{name: row.get(name, _default(dtype)) for name, (dtype, _, _) in TRUTH_COLUMNS.items()}
            for row in rows]


#: Column -> (numpy dtype, unit, description) of the ``TRUTH_VERTICES`` table, in table order.
VERTEX_COLUMNS = {
    "row": ("i4", "", "index of the TRUTH row (0 for the first)"),
    "satellite": ("i4", "", "the row's satellite column"),
    "vertex": ("i4", "", "index of the vertex along the part, from where it enters"),
    "x": ("f8", "pix", "vertex x (the same ends as the TRUTH row's x0, x1)"),
    "y": ("f8", "pix", "vertex y"),
}


def vertices(row):
    """The vertices ``((x, y), ...)`` of the part of the track a TRUTH row describes: the
    row's ``vertices`` when it has them, else its ends ``(x0, y0), (x1, y1)`` (a straight
    track's, or a row read from a file without ``TRUTH_VERTICES``)."""
    path = row.get("vertices")
    if path is None or len(path) < 2:
        return ((float(row["x0"]), float(row["y0"])), (float(row["x1"]), float(row["y1"])))
    return tuple((float(x), float(y)) for x, y in path)


def vertex_records(rows):
    """The ``TRUTH_VERTICES`` records of TRUTH rows: one dict of :data:`VERTEX_COLUMNS` per
    vertex, rows in order, each row's vertices in order along its part."""
    return [{"row": i, "satellite": int(row.get("satellite", -1)), "vertex": k, "x": x, "y": y}
            for i, row in enumerate(rows) for k, (x, y) in enumerate(vertices(row))]
