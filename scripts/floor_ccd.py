"""The floor of a CCD scene as a process: Poisson sky for one CCD, drawn with one numpy call and
written as three image HDUs.

A yardstick for ``inject simulate`` timed end to end (start-up included): the process imports
numpy, GalSim and astropy (as ``inject simulate`` does), draws Poisson sky for the default ITL
CCD (4072 x 4000) with one ``Generator.poisson`` call, and writes it to FITS as IMAGE
(float32), MASK (int32, zeros) and VARIANCE (float32, the sky level), with astropy's
``writeto``. Nothing of inject is imported.

Usage::

    python scripts/floor_ccd.py OUT.fits [--sky 464.709] [--nx 4072] [--ny 4000]

The default sky is that of ``sample_fields/default.yaml`` (g, 30 s, dark sky, z = 70 deg:
``inject.config.sky_level``), in electrons per pixel.
"""
import argparse

import galsim  # noqa: F401  (imported for its start-up cost, as inject simulate imports it)
import numpy as np
from astropy.io import fits


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("output", help="FITS file to write (replaced if it exists)")
    parser.add_argument("--sky", type=float, default=464.709, help="sky level, e- per pixel")
    parser.add_argument("--nx", type=int, default=4072)
    parser.add_argument("--ny", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    shape = (args.ny, args.nx)
    image = np.random.default_rng(args.seed).poisson(args.sky, size=shape).astype(np.float32)
    mask = np.zeros(shape, np.int32)
    variance = np.full(shape, args.sky, np.float32)
    fits.HDUList([fits.PrimaryHDU(), fits.ImageHDU(image, name="IMAGE"),
                  fits.ImageHDU(mask, name="MASK"),
                  fits.ImageHDU(variance, name="VARIANCE")]).writeto(args.output, overwrite=True)


if __name__ == "__main__":
    main()
