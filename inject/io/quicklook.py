"""Quicklook of a simulated CCD (PNG, or JPEG/PDF/SVG by name): z-scaled image, colour bar,
truth tracks."""
import math
import os

import numpy as np

from inject.errors import OutputError
from inject.io.atomic import atomic_path
from inject.trajectory import clip_segment

#: Longest side, in plotted (binned) pixels, of the quicklook image.
MAX_SIDE = 1000

#: The formats a quicklook is written in, by the output's extension (lower case); any other
#: extension gets PNG, except those of :data:`REFUSED`.
FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".pdf": "pdf", ".svg": "svg",
           ".tif": "tiff", ".tiff": "tiff", ".webp": "webp", ".gif": "gif", ".eps": "eps"}
#: Extensions of data formats: a picture under such a name would pass for data.
REFUSED = (".fits", ".fit", ".fts", ".fz", ".gz", ".exr", ".csv", ".json", ".yaml", ".yml",
           ".txt", ".npy", ".hdf5", ".h5")

#: How far each of the two dashed truth lines runs from the track, in points: beside the
#: streak rather than over it, so the streak stays visible and so do the lines, even over a
#: saturated (white) streak and its bleed trails.
TRUTH_OFFSET_PT = 6.0
TRUTH_COLOUR = "#ff8c00"


def quicklook_format(path, what="a quicklook"):
    """The format a picture (:func:`write_quicklook`'s, ``inject pass --plot``'s) is written
    in at ``path``: the one its extension names (:data:`FORMATS`: ``x.jpg`` is JPEG), else PNG.

    Raises
    ------
    OutputError
        The extension is a data format's (:data:`REFUSED`: ``.fits``, ``.csv``, ...); the
        message calls the picture ``what``.
    """
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if ext in REFUSED:
        raise OutputError(f"{path}: {what} is a picture, not {ext[1:].upper()} data: name "
                          f"it .png, .jpg, .pdf, .svg, ...")
    return FORMATS.get(ext, "png")


def bin_factor(shape, max_side=MAX_SIDE):
    """Smallest integer block size bringing both sides of ``shape`` to ``<= max_side``."""
    return max(1, math.ceil(max(shape) / max_side))


def block_mean(image, factor):
    """Block-average ``image`` by ``factor`` x ``factor``.

    Edge blocks that overhang the image average only the pixels they hold, and non-finite
    pixels are ignored, so nothing is trimmed and no NaN spreads.

    Returns
    -------
    ndarray
        Shape ``(ceil(ny / factor), ceil(nx / factor))``; NaN where a block holds no finite
        pixel.
    """
    image = np.asarray(image, dtype=np.float64)
    if factor == 1:
        return image.copy()
    ny, nx = image.shape
    by, bx = -(-ny // factor), -(-nx // factor)
    good = np.isfinite(image)
    padded = np.zeros((by * factor, bx * factor))
    count = np.zeros_like(padded)
    padded[:ny, :nx] = np.where(good, image, 0.0)
    count[:ny, :nx] = good
    sums = padded.reshape(by, factor, bx, factor).sum(axis=(1, 3))
    counts = count.reshape(by, factor, bx, factor).sum(axis=(1, 3))
    out = np.full(sums.shape, np.nan)
    np.divide(sums, counts, out=out, where=counts > 0)
    return out


def zscale_limits(binned):
    from astropy.visualization import ZScaleInterval

    finite = binned[np.isfinite(binned)]
    if finite.size == 0:
        return 0.0, 1.0
    vmin, vmax = ZScaleInterval().get_limits(finite)
    if not vmax > vmin:  # a flat image: give the colour map a non-empty range
        vmin, vmax = vmin - 0.5, vmin + 0.5
    return float(vmin), float(vmax)


def write_quicklook(path, result, overwrite=False, truth=True, title=None):
    """Write a quicklook of a simulated CCD, atomically (see :func:`quicklook_figure`).

    Parameters
    ----------
    path : str or os.PathLike
        Output file, in the format its extension names (:func:`quicklook_format`).
    result : inject.scene.SceneResult
        Only ``image`` and ``truth`` are used.
    overwrite : bool
        Replace an existing ``path``.
    truth, title
        As in :func:`quicklook_figure`.

    Raises
    ------
    OutputError
        ``path`` exists without ``overwrite``, cannot be written, or has an extension of no
        format in :data:`FORMATS`.
    """
    fmt = quicklook_format(path)
    fig = quicklook_figure(result, truth, title)[0]
    with atomic_path(str(path), overwrite) as tmp:
        fig.savefig(tmp, format=fmt)


def quicklook_figure(result, truth=True, title=None):
    """The quicklook as a matplotlib figure (Agg canvas): ``(figure, axes)``.

    The image is block-averaged to at most :data:`MAX_SIDE` pixels a side (stated in the
    title), shown with a z-scale stretch, grey colour map and ``origin='lower'`` (as ds9
    shows the FITS file), axes in unbinned pixels and a colour bar in electrons.

    Parameters
    ----------
    result : inject.scene.SceneResult
    truth : bool
        Mark each truth track from ``(x0, y0)`` to ``(x1, y1)`` by two dashed lines
        :data:`TRUTH_OFFSET_PT` either side of it (orange with a black outline: visible on
        white and on black), labelled with its index in the truth table.
    title : str, optional
        First title line; default ``"inject: simulated CCD"``.
    """
    # The object-oriented API with an explicit Agg canvas: no pyplot global state, no
    # dependence on the user's default backend, safe in worker threads.
    from matplotlib import patheffects
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.transforms import offset_copy

    image = np.asarray(result.image)
    ny, nx = image.shape
    factor = bin_factor(image.shape)
    binned = block_mean(image, factor)
    vmin, vmax = zscale_limits(binned)

    aspect = ny / nx
    width_in = 8.0
    fig = Figure(figsize=(width_in, min(max(width_in * aspect * 0.85 + 0.9, 3.0), 12.0)),
                 dpi=125)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    by, bx = binned.shape
    # Extent in unbinned pixel coordinates (pixel centres at integers), so the truth tracks
    # and axis labels need no conversion; overhanging edge blocks are cut by the limits.
    shown = ax.imshow(binned, origin="lower", cmap="gray", vmin=vmin, vmax=vmax,
                      interpolation="nearest",
                      extent=(-0.5, bx * factor - 0.5, -0.5, by * factor - 0.5))
    ax.set_xlim(-0.5, nx - 0.5)
    ax.set_ylim(-0.5, ny - 0.5)
    ax.set_xlabel("x [pixel]")
    ax.set_ylabel("y [pixel]")
    fig.colorbar(shown, ax=ax, label="electrons", fraction=0.046, pad=0.03)

    missed = []
    rows = result.truth if truth else []
    for index, row in enumerate(rows):
        coords = [row.get(k) for k in ("x0", "y0", "x1", "y1")]
        if any(c is None or not np.isfinite(c) for c in coords):
            continue
        x0, y0, x1, y1 = map(float, coords)
        # Two lines beside the track (offset along its normal on screen, where pixels are
        # square), not over it: the streak stays visible, and so do the lines over a
        # saturated streak (a black outline around orange contrasts with white and black).
        angle = math.atan2(y1 - y0, x1 - x0)
        nx_pt, ny_pt = -math.sin(angle), math.cos(angle)
        for side in (1, -1):
            shifted = offset_copy(ax.transData, fig=fig, x=side * TRUTH_OFFSET_PT * nx_pt,
                                  y=side * TRUTH_OFFSET_PT * ny_pt, units="points")
            ax.plot([x0, x1], [y0, y1], linestyle=(0, (4, 3)), linewidth=1.0,
                    color=TRUTH_COLOUR, transform=shifted, solid_capstyle="butt",
                    path_effects=[patheffects.withStroke(linewidth=2.4, foreground="black")])
        inside = clip_segment(x0, y0, x1, y1, (-0.5, nx - 0.5), (-0.5, ny - 0.5))
        if inside is None:
            missed.append(str(index))
            continue
        # Label at the middle of the visible part (so it stays on the plot), beyond a line.
        xm, ym = (inside[0] + inside[2]) / 2, (inside[1] + inside[3]) / 2
        label = 2.5 * TRUTH_OFFSET_PT
        ax.annotate(str(index), (xm, ym), xytext=(label * nx_pt, label * ny_pt),
                    textcoords="offset points", ha="center", va="center",
                    color=TRUTH_COLOUR, fontsize=9, fontweight="bold",
                    path_effects=[patheffects.withStroke(linewidth=2.0, foreground="black")])
    if missed:
        ax.text(0.01, 0.01, f"off image: {', '.join(missed)}", transform=ax.transAxes,
                color=TRUTH_COLOUR, fontsize=8, va="bottom",
                path_effects=[patheffects.withStroke(linewidth=2.0, foreground="black")])

    binning = (f"binned {factor}x{factor} (block mean)" if factor > 1 else "unbinned")
    lines = [title or "inject: simulated CCD",
             f"{nx} x {ny} px, {binning}, z-scale [{vmin:.4g}, {vmax:.4g}] e-"]
    if truth:
        lines[-1] += f", {len(result.truth)} truth track(s) between dashed lines"
    ax.set_title("\n".join(lines), fontsize=10)
    fig.tight_layout()
    return fig, ax
