"""A synthetic LSST survey of many nights, written as an opsim database (SQLite, table
``observations``, the columns rubin_scheduler writes and ``inject survey`` reads).

Synthetic, not a scheduler's output: every night of ``--years`` (or the first ``--nights``)
from ``--start`` is observed (no weather, no Moon, no downtime), from evening to morning
nautical twilight (the Sun 12 deg below the horizon) at Rubin. While the Sun is between -12
and -18 deg the visits are twilight visits of one 15 s exposure, one every 30 s; in the
dark between them, visits of 30 s (u 38 s) one every 44 s: about 860 visits a night over
the year (690 in January, 1,010 in June). Each visit takes a field of an even grid over
the southern sky above airmass 2 near the meridian (so its RA follows the sidereal time, and
the season), and the same field again ~33 minutes later as LSST's pairs do
(``scripts/make_opsim_night.py``'s fields and choice). Each night's visits are in LSST's
band mix (u 6, g 9, r 22, i 22, z 20, y 21 %, to a visit), one block per band in a random
order. rotSkyPos is rubin_scheduler's (parallactic angle - rotTelPos - 90 deg) with
rotTelPos within +-60 deg per block; seeingFwhmEff is rubin_scheduler's seeing model with a
log-normal seeing at 500 nm about 0.7" per block; skyBrightness is SMTN-002's dark sky at
zenith brightened by the airmass and, in twilight, by 10^(0.25 (h + 18)) for the Sun's
altitude h (3.75 mag at -12 deg).

The Sun's position is the Astronomical Almanac's low-precision formula (0.01 deg), enough for
the twilight's edges. Seeds: ``--seed`` makes a numpy SeedSequence, spawning one stream per
night, so a night's visits are the same whatever ``--nights`` or ``--years`` says.

Usage::

    python scripts/make_synthetic_survey.py -o out/survey10.db [--years 10] [--nights N]
        [--start 2026-01-01] [--seed 7]
"""
import argparse
import math
import os
import sqlite3
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import make_opsim_night as night  # noqa: E402  (the night's fields, seeing and schema)

from inject.io.atomic import atomic_path  # noqa: E402

SITE_LON = night.SITE_LON
#: The columns written: make_opsim_night's and the sky and the Sun's altitude.
SCHEMA = night.SCHEMA + ("skyBrightness REAL", "sunAlt REAL")
#: SMTN-002's dark sky at zenith, mag/arcsec^2.
DARK_SKY = {"u": 23.05, "g": 22.25, "r": 21.20, "i": 20.46, "z": 19.61, "y": 18.60}
#: Seconds between the starts of two visits: twilight (15 s exposures) and dark.
TWILIGHT_SLOT_S = 30.0
DARK_SLOT_S = 44.0
TWILIGHT_EXPTIME_S = 15.0
#: The night's edges: nautical (LSST starts) and astronomical twilight, Sun's altitude, deg.
NAUTICAL_DEG, ASTRONOMICAL_DEG = -12.0, -18.0
#: Days in a year of the survey.
YEAR_DAYS = 365.25


def sun_altitude_deg(mjd_utc):
    """The Sun's altitude at Rubin, deg (the Astronomical Almanac's low-precision Sun and
    GMST; UT1 taken as UTC)."""
    n = np.asarray(mjd_utc, float) - 51544.5  # days from J2000.0
    mean_lon = np.radians((280.460 + 0.9856474 * n) % 360.0)
    anomaly = np.radians((357.528 + 0.9856003 * n) % 360.0)
    lam = mean_lon + np.radians(1.915) * np.sin(anomaly) + np.radians(0.020) * np.sin(
        2.0 * anomaly)
    eps = np.radians(23.439 - 4e-7 * n)
    ra = np.degrees(np.arctan2(np.cos(eps) * np.sin(lam), np.cos(lam)))
    dec = np.degrees(np.arcsin(np.sin(eps) * np.sin(lam)))
    lst = (280.46061837 + 360.98564736629 * n + SITE_LON) % 360.0
    alt, _ = night.altaz((lst - ra + 180.0) % 360.0 - 180.0, dec)
    return alt


def local_sidereal_deg(mjd_utc):
    """Local mean sidereal time at Rubin, deg."""
    n = np.asarray(mjd_utc, float) - 51544.5
    return (280.46061837 + 360.98564736629 * n + SITE_LON) % 360.0


def night_edges(mjd_noon):
    """MJDs (UTC) of a night's evening -12 and -18 deg and morning -18 and -12 deg, from
    the Sun every minute of the 24 h after ``mjd_noon`` (local noon at Rubin)."""
    t = mjd_noon + np.arange(24 * 60 + 1) / 1440.0
    alt = sun_altitude_deg(t)
    nautical = np.flatnonzero(alt < NAUTICAL_DEG)
    astronomical = np.flatnonzero(alt < ASTRONOMICAL_DEG)
    return (t[nautical[0]], t[astronomical[0]], t[astronomical[-1]] + 1.0 / 1440.0,
            t[nautical[-1]] + 1.0 / 1440.0)


def visit_starts(edges):
    """Start MJDs (UTC) of a night's visits and whether each is a twilight visit."""
    e12, e18, m18, m12 = edges

    def slots(a, b, step_s):
        return a + np.arange(int((b - a) * 86400.0 // step_s)) * step_s / 86400.0

    parts = [(slots(e12, e18, TWILIGHT_SLOT_S), True), (slots(e18, m18, DARK_SLOT_S), False),
             (slots(m18, m12, TWILIGHT_SLOT_S), True)]
    times = np.concatenate([p for p, _ in parts])
    twilight = np.concatenate([np.full(len(p), flag) for p, flag in parts])
    return times, twilight


def band_counts(n):
    """Visits per band for ``n`` visits in LSST's mix (largest remainders)."""
    shares = np.array([night.BAND_SHARE[b] for b in "ugrizy"])
    raw = shares * n
    counts = np.floor(raw).astype(int)
    counts[np.argsort(raw - counts)[::-1][:n - counts.sum()]] += 1
    return dict(zip("ugrizy", counts))


def build_night(index, mjd_noon, rng, first_id, fields):
    """One night's visits as tuples in :data:`SCHEMA`'s order."""
    from astropy.time import Time

    ras, decs = fields
    # sin(alt) = sin(lat) sin(dec) + cos(lat) cos(dec) cos(HA): the fields' parts once a night.
    lat = math.radians(night.SITE_LAT)
    fixed = math.sin(lat) * np.sin(np.radians(decs))
    varying = math.cos(lat) * np.cos(np.radians(decs))
    above = math.sin(math.radians(30.0))  # airmass 2
    times, twilight = visit_starts(night_edges(mjd_noon))
    n = len(times)
    order = rng.permutation(list("ugrizy"))
    counts = band_counts(n)
    bands = np.concatenate([[b] * counts[b] for b in order])
    blocks = np.concatenate([[k] * counts[b] for k, b in enumerate(order)])
    block_rot = rng.uniform(-60.0, 60.0, size=6)
    seeing500 = 0.7 * np.exp(rng.normal(0.0, 0.25, size=6))
    lst = local_sidereal_deg(times)
    sun = sun_altitude_deg(times)
    tai = Time(times, format="mjd", scale="utc").tai.mjd
    rows, pending = [], {}
    for k in range(n):
        band, block = str(bands[k]), int(blocks[k])
        ha = (lst[k] - ras + 180.0) % 360.0 - 180.0
        sin_alt = fixed + varying * np.cos(np.radians(ha))
        field = pending.pop(k, None)
        if field is None or sin_alt[field] < above:
            ok = np.flatnonzero(sin_alt > above)
            weight = np.exp(-np.abs(ha[ok]) / 22.5)  # 1.5 h of hour angle
            field = int(ok[rng.choice(len(ok), p=weight / weight.sum())])
            later = int(np.searchsorted(times, times[k] + 33.0 / 1440.0))
            if later < n and later not in pending:
                pending[later] = field
        alt_f, az_f = night.altaz(ha[field], decs[field])
        airmass = 1.0 / math.sin(math.radians(float(alt_f)))
        pa = float(night.parallactic_deg(ha[field], decs[field]))
        rot_tel = float(np.clip(block_rot[block] + rng.normal(0.0, 2.0), -90.0, 90.0))
        if twilight[k]:
            exptime = TWILIGHT_EXPTIME_S
        else:
            exptime = 38.0 if band == "u" else 30.0
        s500 = float(seeing500[block] * np.exp(rng.normal(0.0, 0.05)))
        fwhm_atm = s500 * airmass ** 0.6 * (500.0 / night.WAVELENGTH_NM[band]) ** 0.3
        fwhm_eff = 1.16 * math.sqrt((0.39 * airmass ** 0.6) ** 2 + 1.04 * fwhm_atm ** 2)
        sky = DARK_SKY[band] - 2.5 * math.log10(airmass) - 2.5 * 0.25 * max(
            float(sun[k]) - ASTRONOMICAL_DEG, 0.0)
        mjd = float(tai[k])
        row = {"observationId": first_id + k, "fieldRA": float(ras[field]),
               "fieldDec": float(decs[field]), "observationStartMJD": mjd,
               "flush_by_mjd": mjd + 1.0 / 24, "visitExposureTime": exptime, "band": band,
               "filter": band, "rotSkyPos": (pa - rot_tel - 90.0) % 360.0,
               "rotTelPos": rot_tel, "numExposures": 1, "airmass": airmass,
               "seeingFwhm500": s500, "seeingFwhmEff": fwhm_eff,
               "seeingFwhmGeom": 0.822 * fwhm_eff + 0.052, "altitude": float(alt_f),
               "azimuth": float(az_f), "paraAngle": pa, "night": index + 1,
               "visitTime": exptime + 1.0,
               "note": ("twilight" if twilight[k] else "dark")
               + ", synthetic (scripts/make_synthetic_survey.py)",
               "skyBrightness": sky, "sunAlt": float(sun[k])}
        rows.append(tuple(row[c.split()[0]] for c in SCHEMA))
    return rows


def write_survey(path, start, n_nights, seed, overwrite=False, progress=None):
    """Write ``n_nights`` nights from the local evening of ``start`` (YYYY-MM-DD); returns
    the visits per night."""
    from astropy.time import Time

    # Local noon at Rubin is ~16:43 UTC.
    noon0 = Time(f"{start}T16:43:00", scale="utc").mjd
    streams = np.random.SeedSequence(seed).spawn(n_nights)
    fields = night.field_grid()
    names = [c.split()[0] for c in SCHEMA]
    per_night = []
    with atomic_path(path, overwrite) as tmp:
        con = sqlite3.connect(tmp)
        try:
            con.execute(f"CREATE TABLE observations ({', '.join(SCHEMA)})")
            first = 0
            for k in range(n_nights):
                rows = build_night(k, noon0 + k, np.random.default_rng(streams[k]), first,
                                   fields)
                con.executemany(f"INSERT INTO observations VALUES "
                                f"({', '.join('?' * len(names))})", rows)
                first += len(rows)
                per_night.append(len(rows))
                if progress is not None:
                    progress(k + 1, first)
            con.commit()
        finally:
            con.close()
    return per_night


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", required=True, help="SQLite file to write")
    parser.add_argument("--years", type=float, default=10.0,
                        help="years of nights from --start (default 10)")
    parser.add_argument("--nights", type=int,
                        help="N nights from --start (default: --years' nights)")
    parser.add_argument("--start", default="2026-01-01",
                        help="local date of the first night's evening (default 2026-01-01)")
    parser.add_argument("--seed", type=int, default=7,
                        help="seed of the numpy SeedSequence (one stream per night)")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args()
    if not args.years > 0:
        parser.error(f"--years {args.years}: must be > 0")
    if args.nights is not None and args.nights < 1:
        parser.error(f"--nights {args.nights}: must be >= 1")
    n_nights = args.nights if args.nights is not None else int(round(args.years * YEAR_DAYS))
    step = max(1, n_nights // 20)

    def progress(done, visits):
        if done % step == 0 or done == n_nights:
            print(f"make_synthetic_survey: night {done}/{n_nights}, {visits} visits",
                  file=sys.stderr, flush=True)

    per_night = write_survey(args.output, args.start, n_nights, args.seed, args.overwrite,
                             progress)
    print(f"{args.output}: {sum(per_night)} visits in {n_nights} nights from {args.start} "
          f"({min(per_night)}-{max(per_night)} a night, mean {np.mean(per_night):.0f}); "
          f"synthetic")


if __name__ == "__main__":
    main()
