"""A synthetic night of LSST visits, written as an opsim database (SQLite, table
``observations``, the columns rubin_scheduler writes).

Not a scheduler: a plausible night for ``inject survey`` to read. The night runs from the end
of evening nautical twilight (Sun 12 deg below the horizon, when LSST starts) to the start of
morning twilight at Rubin; its ~550 visits are spread evenly over it with a few seconds of
jitter, each 30 s (one exposure, or two snaps of 15 s with ``--snaps 2``; u 38 s, as the v3
baseline). Fields come from an even grid over the southern sky (dec -85 to +10 deg, ~3.5 deg
apart), each visit taking a field above airmass 2 (altitude > 30 deg) near the meridian
(weight exp(-|hour angle| / 1.5 h)), and the same field again ~33 min later as LSST's pairs do.
Bands come in blocks of ~45 min (ugrizy in LSST's proportions: 6, 9, 22, 22, 20, 21 %).
rotSkyPos follows rubin_scheduler's convention, parallactic angle - rotTelPos - 90 deg, with
rotTelPos drawn within +-60 deg each block; seeingFwhmEff is rubin_scheduler's seeing model
(1.16 sqrt(FWHMsys^2 + 1.04 FWHMatm^2), FWHMsys = 0.39" X^0.6, FWHMatm = s500 X^0.6
(500 nm / lambda)^0.3) with s500 log-normal about 0.7".

Usage::

    python scripts/make_opsim_night.py -o out/night.db [--night 2026-06-15] [--visits 550]
        [--snaps 1] [--seed 7] [--csv out/night.csv]
"""
import argparse
import math
import sqlite3

import numpy as np
from astropy import units as u
from astropy.coordinates import AltAz, EarthLocation, get_sun
from astropy.time import Time

from inject.io.atomic import atomic_path

SITE_LAT, SITE_LON, SITE_HEIGHT = -30.2446, -70.7494, 2647.0
#: Effective wavelengths, nm (LSST's filters).
WAVELENGTH_NM = {"u": 367.0, "g": 482.5, "r": 622.2, "i": 754.5, "z": 869.1, "y": 971.0}
BAND_SHARE = {"u": 0.06, "g": 0.09, "r": 0.22, "i": 0.22, "z": 0.20, "y": 0.21}
SCHEMA = ("observationId INTEGER PRIMARY KEY", "fieldRA REAL", "fieldDec REAL",
          "observationStartMJD REAL", "flush_by_mjd REAL", "visitExposureTime REAL",
          "band TEXT", "filter TEXT", "rotSkyPos REAL", "rotTelPos REAL", "numExposures INTEGER",
          "airmass REAL", "seeingFwhm500 REAL", "seeingFwhmEff REAL", "seeingFwhmGeom REAL",
          "altitude REAL", "azimuth REAL", "paraAngle REAL", "night INTEGER", "visitTime REAL",
          "note TEXT")


def field_grid(spacing_deg=3.5, dec_min=-85.0, dec_max=10.0):
    """Field centres about ``spacing_deg`` apart (rings of constant dec)."""
    ras, decs = [], []
    for ring, dec in enumerate(np.arange(dec_min, dec_max + 1e-9, spacing_deg)):
        n = max(1, int(round(360.0 * math.cos(math.radians(dec)) / spacing_deg)))
        offset = (0.37 * ring) % 1.0  # rings not aligned in RA
        ras += list((np.arange(n) + offset) * 360.0 / n % 360.0)
        decs += [dec] * n
    return np.array(ras), np.array(decs)


def dark_interval(night, sun_alt_deg=-12.0):
    """(start, end) UTC Times of the night starting on the local evening of ``night``."""
    site = EarthLocation.from_geodetic(SITE_LON * u.deg, SITE_LAT * u.deg, SITE_HEIGHT * u.m)
    # Local noon at Rubin is ~16:43 UTC: scan from there, one minute apart.
    times = Time(f"{night}T16:43:00", scale="utc") + np.arange(0, 24 * 60) * u.min
    alt = get_sun(times).transform_to(AltAz(obstime=times, location=site)).alt.deg
    dark = np.flatnonzero(alt < sun_alt_deg)
    return times[dark[0]], times[dark[-1]]


def parallactic_deg(ha_deg, dec_deg):
    h, d, p = np.radians(ha_deg), np.radians(dec_deg), math.radians(SITE_LAT)
    return np.degrees(np.arctan2(np.sin(h), math.tan(p) * np.cos(d) - np.sin(d) * np.cos(h)))


def altaz(ha_deg, dec_deg):
    h, d, p = np.radians(ha_deg), np.radians(dec_deg), math.radians(SITE_LAT)
    alt = np.arcsin(np.sin(p) * np.sin(d) + np.cos(p) * np.cos(d) * np.cos(h))
    az = np.arctan2(-np.cos(d) * np.sin(h),
                    np.sin(d) * np.cos(p) - np.cos(d) * np.cos(h) * np.sin(p))
    return np.degrees(alt), np.degrees(az) % 360.0


def build(night, n_visits, snaps, seed):
    """The night's visits as a list of column dicts."""
    rng = np.random.default_rng(seed)
    start, end = dark_interval(night)
    span = (end - start).to_value(u.s)
    step = span / n_visits
    times = start + (np.arange(n_visits) * step + rng.uniform(0, 0.15 * step, n_visits)) * u.s
    lst = times.sidereal_time("mean", longitude=SITE_LON * u.deg).deg
    ras, decs = field_grid()
    bands = list(BAND_SHARE)
    block_s = 45 * 60
    block_band = rng.choice(bands, size=int(span // block_s) + 2,
                            p=np.array(list(BAND_SHARE.values())))
    block_rot = rng.uniform(-60.0, 60.0, size=len(block_band))
    seeing500 = 0.7 * np.exp(rng.normal(0.0, 0.25, size=len(block_band)))
    rows, pending = [], {}
    for k, t in enumerate(times):
        block = int((t - start).to_value(u.s) // block_s)
        band = str(block_band[block])
        ha = (lst[k] - ras + 180.0) % 360.0 - 180.0
        alt, _ = altaz(ha, decs)
        field = pending.pop(k, None)
        if field is None or alt[field] < 30.0:
            ok = np.flatnonzero(alt > 30.0)
            weight = np.exp(-np.abs(ha[ok]) / 22.5)  # 1.5 h of hour angle
            field = int(rng.choice(ok, p=weight / weight.sum()))
            later = k + int(round(33 * 60 / step))  # the pair's second visit
            if later < n_visits and later not in pending:
                pending[later] = field
        alt_f, az_f = altaz(ha[field], decs[field])
        airmass = 1.0 / math.sin(math.radians(float(alt_f)))
        pa = float(parallactic_deg(ha[field], decs[field]))
        rot_tel = float(np.clip(block_rot[block] + rng.normal(0.0, 2.0), -90.0, 90.0))
        exptime = 38.0 if band == "u" else 30.0
        n_exp = 1 if band == "u" else snaps
        s500 = float(seeing500[block] * np.exp(rng.normal(0.0, 0.05)))
        fwhm_atm = s500 * airmass ** 0.6 * (500.0 / WAVELENGTH_NM[band]) ** 0.3
        fwhm_sys = 0.39 * airmass ** 0.6
        fwhm_eff = 1.16 * math.sqrt(fwhm_sys ** 2 + 1.04 * fwhm_atm ** 2)
        mjd_tai = float(t.tai.mjd)
        rows.append({
            "observationId": k, "fieldRA": float(ras[field]), "fieldDec": float(decs[field]),
            "observationStartMJD": mjd_tai, "flush_by_mjd": mjd_tai + 1.0 / 24,
            "visitExposureTime": exptime, "band": band, "filter": band,
            "rotSkyPos": (pa - rot_tel - 90.0) % 360.0, "rotTelPos": rot_tel,
            "numExposures": n_exp, "airmass": airmass, "seeingFwhm500": s500,
            "seeingFwhmEff": fwhm_eff, "seeingFwhmGeom": 0.822 * fwhm_eff + 0.052,
            "altitude": float(alt_f), "azimuth": float(az_f), "paraAngle": pa, "night": 1,
            "visitTime": exptime + 2.0 * (n_exp - 1) + n_exp * 1.0,
            "note": "synthetic (scripts/make_opsim_night.py)"})
    return rows


def write_sqlite(path, rows, overwrite=False):
    names = [c.split()[0] for c in SCHEMA]
    with atomic_path(path, overwrite) as tmp:
        con = sqlite3.connect(tmp)
        try:
            con.execute(f"CREATE TABLE observations ({', '.join(SCHEMA)})")
            con.executemany(f"INSERT INTO observations VALUES ({', '.join('?' * len(names))})",
                            [tuple(r[n] for n in names) for r in rows])
            con.commit()
        finally:
            con.close()


def write_csv(path, rows, overwrite=False):
    import csv

    with atomic_path(path, overwrite) as tmp:
        with open(tmp, "w", newline="") as stream:
            writer = csv.DictWriter(stream, list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", required=True, help="SQLite file to write")
    parser.add_argument("--night", default="2026-06-15",
                        help="local date of the night's evening (default 2026-06-15)")
    parser.add_argument("--visits", type=int, default=550)
    parser.add_argument("--snaps", type=int, choices=(1, 2), default=1,
                        help="exposures per visit outside u (1: 1 x 30 s; 2: 2 x 15 s)")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--csv", help="also write the visits as a CSV")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args()
    rows = build(args.night, args.visits, args.snaps, args.seed)
    write_sqlite(args.output, rows, args.overwrite)
    if args.csv:
        write_csv(args.csv, rows, args.overwrite)
    first, last = rows[0]["observationStartMJD"], rows[-1]["observationStartMJD"]
    bands = {b: sum(r["band"] == b for r in rows) for b in "ugrizy"}
    print(f"{args.output}: {len(rows)} visits from MJD {first:.4f} to {last:.4f} (TAI), "
          f"{(last - first) * 24:.2f} h; bands {bands}; airmass "
          f"{min(r['airmass'] for r in rows):.2f}-{max(r['airmass'] for r in rows):.2f}")


if __name__ == "__main__":
    main()
