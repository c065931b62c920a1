"""``mosaic.png``: a whole focal-plane exposure as one picture, for a person to look at.

Each CCD's IMAGE is block-averaged and drawn at its place in focal-plane millimetres, each
block at its true size (a partial last block cut at the CCD's edge), so the gaps between CCDs
and rafts are to scale; one z-scale stretch for all CCDs; detector names on
each; the true track of every satellite drawn over it (dashed, in focal-plane mm). CCDs of the
exposure that have no file of this scene yet are filled grey; the gaps are dark blue.
"""
import os

import numpy as np

from inject.io.atomic import atomic_path
from inject.io.quicklook import block_mean, zscale_limits

#: Default binning: a full focal plane (63 400 px across) about 1600 plotted pixels wide.
DEFAULT_BIN = 40


def binned_ccds(fscene, outdir, factor):
    """``{CCD: binned IMAGE}`` for every CCD of the scene with a file of this scene in
    ``outdir`` (its ``FPSCENE`` card: a file of another scene's run, or of none, is not
    shown)."""
    from astropy.io import fits

    out = {}
    for ccd in fscene.ccds:
        path = os.path.join(outdir, f"{ccd.name}.fits")
        if not os.path.exists(path):
            continue
        try:
            with fits.open(path, memmap=True) as hdus:
                if hdus[0].header.get("FPSCENE") != fscene.digest[:16]:
                    continue
                image = np.asarray(hdus["IMAGE"].data, dtype=np.float32)  # native order
        except (OSError, ValueError, KeyError):
            continue  # not a CCD file of this scene's run (a stray file, half a file)
        out[ccd] = block_mean(image, factor)
    return out


def block_extent(bounds, shape, binned_shape, factor):
    """``(x0, x1, y0, y1)`` mm over which to draw a CCD's binned image so that every block
    spans ``factor`` pixels: the last block of a row or column, partly beyond the CCD's
    ``shape`` (``ceil(n / factor)`` blocks), overhangs its edge (clip it to ``bounds``)."""
    x0, x1, y0, y1 = bounds
    (ny, nx), (by, bx) = shape, binned_shape
    return (x0, x0 + (x1 - x0) * bx * factor / nx, y0, y0 + (y1 - y0) * by * factor / ny)


def track_paths(fscene):
    """Each satellite's track in focal-plane mm, a line clipped to the focal plane."""
    from inject.camera.layout import extent_mm
    from inject.trajectory import clip_segment

    xmin, xmax, ymin, ymax = extent_mm()
    out = []
    for track in fscene.tracks:
        if track.kind == "line":
            ends = clip_segment(track.xs[0], track.ys[0], track.xs[1], track.ys[1],
                                (xmin, xmax), (ymin, ymax))
            out.append(([], []) if ends is None else ((ends[0], ends[2]), (ends[1], ends[3])))
        else:
            out.append((track.xs, track.ys))
    return out


def write_mosaic(path, fscene, outdir, factor=DEFAULT_BIN, overwrite=True,
                 dpi=100, names=True, title=None):
    """Write the mosaic of the CCD files in ``outdir`` to ``path`` (PNG), atomically.

    Parameters
    ----------
    path : str
    fscene : inject.exposure.scene.FocalScene
    outdir : str
        Where the CCD files are (``<detector>.fits``).
    factor : int
        Block size of the binning, pixels.
    overwrite : bool
        The mosaic is remade by every run into ``outdir``.
    names : bool
        Write each detector's name on it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Rectangle

    from inject.camera.layout import PIXEL_MM, extent_mm
    from inject.exposure.plan import ccd_shape

    binned = binned_ccds(fscene, outdir, factor)
    sample = np.concatenate([b[np.isfinite(b)].ravel()[::7] for b in binned.values()]) \
        if binned else np.zeros(1)
    vmin, vmax = zscale_limits(sample)
    xmin, xmax, ymin, ymax = extent_mm()
    side_px = (xmax - xmin) / (PIXEL_MM * factor)
    inches = max(4.0, side_px / dpi)
    fig = Figure(figsize=(inches, inches * (ymax - ymin) / (xmax - xmin) + 0.4))
    FigureCanvasAgg(fig)
    ax = fig.add_axes([0.0, 0.0, 1.0, 0.97])
    ax.set_facecolor("#20304a")  # the gaps: no silicon
    for ccd in fscene.ccds:
        shape = ccd_shape(fscene, ccd)
        x0, x1, y0, y1 = ccd.bounds_mm(0.0, shape)
        if ccd in binned:
            shown = ax.imshow(binned[ccd], origin="lower", cmap="gray", vmin=vmin, vmax=vmax,
                              extent=block_extent((x0, x1, y0, y1), shape, binned[ccd].shape,
                                                  factor), interpolation="nearest")
            # The overhang of the last blocks is cut at the CCD's edge: the gaps stay to scale.
            shown.set_clip_path(Rectangle((x0, y0), x1 - x0, y1 - y0, transform=ax.transData))
        else:  # not rendered (yet): grey, so it is not mistaken for a gap
            ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fc="#5a6270", lw=0.4,
                                   ec="#8d99ae"))
        if names:
            fx0, fx1, fy0, fy1 = ccd.bounds_mm()
            ax.text(0.5 * (fx0 + fx1), fy1 - 2.0, ccd.name, ha="center", va="top",
                    fontsize=max(3.0, inches * 0.28), color="#ffd166")
    for i, (xs, ys) in enumerate(track_paths(fscene)):
        if len(xs):
            ax.plot(xs, ys, ls=(0, (4, 4)), lw=0.5, alpha=0.7, color="#ef476f",
                    label=f"satellite {i}")
    ax.set_xlim(xmin - 2, xmax + 2)
    ax.set_ylim(ymin - 2, ymax + 2)
    ax.set_aspect("equal")
    ax.set_xticks([])  # no axes drawn, but keep the axes' background: it shows the gaps
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)
    pointing = fscene.pointing
    fig.suptitle(title or (f"inject focal plane: {len(binned)} of {len(fscene.ccds)} CCDs, "
                           f"binned {factor}x{factor}, z-scale [{vmin:.0f}, {vmax:.0f}]; "
                           f"ra {pointing.ra_deg:g} dec {pointing.dec_deg:g} rotSkyPos "
                           f"{pointing.rotation_deg:g}; dashed: true tracks"),
                 fontsize=max(5.0, inches * 0.45), y=0.995)
    with atomic_path(path, overwrite) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, facecolor="white")
    return len(binned)
