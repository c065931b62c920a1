"""``inject survey``: the plan of a night of visits against a constellation.

The crossings are checked against an independent computation of every satellite's pass with
skyfield (its own frames, Earth orientation and time scales; the light time, the aberration,
the gnomonic projection, the rotator, the distortion and the CCD layout written here from
their definitions), the pixel counts against closed forms, the mask width against the
simulator's own STREAK plane, and bad inputs against one-line errors that leave nothing
behind.
"""
import csv
import math
import os
import sqlite3

import numpy as np
import pytest

from inject.camera import layout as fp
from inject.survey.plan import run_spans, union_pixels

# --- small opsim databases ------------------------------------------------------------------

COLUMNS = ("observationId", "observationStartMJD", "fieldRA", "fieldDec", "rotSkyPos",
           "band", "visitExposureTime", "numExposures", "seeingFwhmEff")


def write_opsim(path, rows, columns=COLUMNS, table="observations"):
    """An SQLite file in the opsim schema (the columns given) holding ``rows``."""
    con = sqlite3.connect(path)
    types = {"band": "TEXT", "filter": "TEXT", "observationId": "INTEGER",
             "numExposures": "INTEGER"}
    fields = ", ".join(f"{c} {types.get(c, 'REAL')}" for c in columns)
    con.execute(f"CREATE TABLE {table} ({fields})")
    con.executemany(f"INSERT INTO {table} VALUES ({', '.join('?' * len(columns))})",
                    [tuple(r[c] for c in columns) for r in rows])
    con.commit()
    con.close()
    return path


MODEL = "shape: {type: box, length: 7.25, width: 2.65}\nmag: 5.0\nref_range: 550\n"


def write_constellation(folder, body, name="const.yaml"):
    path = os.path.join(folder, name)
    with open(path, "w") as stream:
        stream.write(MODEL + body)
    return path


def read_csv(path):
    with open(path, newline="") as stream:
        return list(csv.DictReader(stream))


# --- the independent pass: skyfield ---------------------------------------------------------

SITE = (-30.2446, -70.7494, 2647.0)
C_KM_S = 299792.458
#: obs_lsst's plate scale ("/mm) and radial distortion (angle = s (r - D3 r^3 - D5 r^5)).
PLATE = 20.005867576692737
D3, D5 = 8.33713991e-9, 1.41389858e-15
ITL_RAFTS = {"R01", "R02", "R03", "R10", "R20", "R41", "R42", "R43"}


def ccd_boxes():
    """Every science CCD's pixel area in focal-plane mm, from obs_lsst's nominal layout:
    raft Rij at (127 (j - 2), 127 (i - 2)) mm, CCD Skl at (42.25 (l - 1), 42.25 (k - 1)) mm
    from it, 10 um pixels; e2v 4096 x 4004 with the reference pixel (2047.5, 2001.5), ITL
    4072 x 4000 with (2036.5, 2000.5)."""
    boxes = {}
    for i in range(5):
        for j in range(5):
            if (i, j) in ((0, 0), (0, 4), (4, 0), (4, 4)):
                continue
            raft = f"R{i}{j}"
            nx, ny, rx, ry = ((4072, 4000, 2036.5, 2000.5) if raft in ITL_RAFTS
                              else (4096, 4004, 2047.5, 2001.5))
            for k in range(3):
                for m in range(3):
                    cx = 127.0 * (j - 2) + 42.25 * (m - 1)
                    cy = 127.0 * (i - 2) + 42.25 * (k - 1)
                    boxes[f"{raft}_S{k}{m}"] = (
                        cx + (-0.5 - rx) * 0.01, cx + (nx - 0.5 - rx) * 0.01,
                        cy + (-0.5 - ry) * 0.01, cy + (ny - 0.5 - ry) * 0.01)
    return boxes


BOXES = ccd_boxes()


def radius_mm(theta_rad):
    """Focal-plane radius of a field angle: the distortion polynomial solved by bisection."""
    target = np.degrees(theta_rad) * 3600.0 / PLATE
    lo, hi = np.zeros_like(target), np.full_like(target, 500.0)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        low = mid - D3 * mid ** 3 - D5 * mid ** 5 < target
        lo, hi = np.where(low, mid, lo), np.where(low, hi, mid)
    return 0.5 * (lo + hi)


BOX_ARRAY = np.array(list(BOXES.values()))
BOX_NAMES = list(BOXES)


def clipped_lengths(x0, y0, x1, y1):
    """Length (mm) of each segment inside each CCD box (Liang-Barsky slab clipping), shape
    (n_segments, n_boxes); 0 where it misses."""
    xmin, xmax, ymin, ymax = (BOX_ARRAY[:, k][None, :] for k in range(4))
    dx, dy = (x1 - x0)[:, None], (y1 - y0)[:, None]
    t0, t1 = np.zeros((len(x0), len(BOX_ARRAY))), np.ones((len(x0), len(BOX_ARRAY)))
    with np.errstate(divide="ignore", invalid="ignore"):
        for p, q in ((-dx, x0[:, None] - xmin), (dx, xmax - x0[:, None]),
                     (-dy, y0[:, None] - ymin), (dy, ymax - y0[:, None])):
            r = q / p
            t0 = np.where(p < 0, np.maximum(t0, r), t0)
            t1 = np.where(p > 0, np.minimum(t1, r), t1)
            t1 = np.where((p == 0) & (q < 0), -1.0, t1)  # parallel and outside
    return np.maximum(t1 - t0, 0.0) * np.hypot(dx, dy)


class Skyfield:
    """Every satellite's apparent track in one visit, computed with skyfield."""

    def __init__(self):
        from astropy.utils import iers as astropy_iers
        from skyfield.api import load, wgs84
        from skyfield.data import iers
        from skyfield.timelib import Timescale

        # UT1 and polar motion from the IERS table astropy bundles (no download), as inject
        # uses: skyfield's own predictions for 2026 differ by 28 ms of UT1, i.e. 11 m of the
        # site's motion, 3" at LEO ranges; polar motion moves the site by ~10 m too.
        with load.open(astropy_iers.IERS_A_FILE) as stream:
            finals = iers.parse_x_y_dut1_from_finals_all(stream)
        daily_tt, daily_delta_t, leap_dates, leap_offsets = iers.build_timescale_arrays(
            finals["utc_mjd"], finals["dut1"])
        self.ts = Timescale((daily_tt, daily_delta_t), leap_dates, leap_offsets)
        iers.install_polar_motion_table(self.ts, finals)
        self.site = wgs84.latlon(SITE[0], SITE[1], elevation_m=SITE[2])

    def visit(self, mjd_tai, exptime, ra, dec, rotation, step_s=1.0):
        """What every satellite of a visit shares: times, the site, the Earth's velocity,
        the Sun, the boresight's axes."""
        from astropy import units as u
        from astropy.coordinates import get_body_barycentric_posvel, get_sun
        from astropy.time import Time

        t_s = np.arange(0.0, exptime + 1e-9, step_s)
        t = self.ts.tai_jd(mjd_tai + 2400000.5 + t_s / 86400.0)
        obs = self.site.at(t)
        times = Time(mjd_tai + t_s / 86400.0, format="mjd", scale="tai")
        sun = get_sun(times).cartesian.xyz.to_value(u.km)
        a0, d0 = math.radians(ra), math.radians(dec)
        centre = np.array([math.cos(d0) * math.cos(a0), math.cos(d0) * math.sin(a0),
                           math.sin(d0)])
        east = np.array([-math.sin(a0), math.cos(a0), 0.0])
        return {"t_s": t_s, "t": t, "r_obs": obs.position.km, "v_obs": obs.velocity.km_per_s,
                "v_earth": get_body_barycentric_posvel("earth", times)[1].xyz.to_value(
                    u.km / u.s),
                "sun": sun / np.linalg.norm(sun, axis=0), "centre": centre, "east": east,
                "north": np.cross(centre, east), "rotation": rotation}

    def track(self, sat, v):
        """Focal-plane field angles (rad, gnomonic) of the satellite at the visit's times,
        whether it is sunlit (None where within 60 km of the Earth's shadow cylinder) and
        whether it is in front of the boresight (the boresights are above 30 deg: the field's
        satellites are far above the horizon)."""
        t, r_obs = v["t"], v["r_obs"]
        geo = sat.at(t)
        r_geo, v_geo = geo.position.km, geo.velocity.km_per_s
        # Light time: the satellite where it was when the light left it, tau = |r - r_obs| / c
        # solved by iteration; over tau (< 10 ms) its path is straight to a micrometre.
        tau = np.zeros(len(v["t_s"]))
        for _ in range(3):
            r_sat = r_geo - v_geo * tau
            tau = np.linalg.norm(r_sat - r_obs, axis=0) / C_KM_S
        d = r_sat - r_obs
        u_sat = d / np.linalg.norm(d, axis=0)
        # The satellite's light is aberrated by the site's velocity about the geocentre alone
        # (the geocentric frame moves with the Earth); the ICRS direction of the star seen at
        # the same place takes the Earth's velocity about the barycentre off as well.
        u_app = _aberrate(u_sat, v["v_obs"] / C_KM_S)
        u_icrs = _aberrate(u_app, -(v["v_earth"] + v["v_obs"]) / C_KM_S)
        cz = v["centre"] @ u_icrs
        xi, eta = (v["east"] @ u_icrs) / cz, (v["north"] @ u_icrs) / cz  # gnomonic, radians
        # rotSkyPos: focal-plane +y at position angle `rotation` (north through east), +x at
        # rotation - 90 deg (west at rotation 0).
        c, s = math.cos(math.radians(v["rotation"])), math.sin(math.radians(v["rotation"]))
        fx, fy = -c * xi + s * eta, s * xi + c * eta
        # Sunlit: outside the Earth's shadow cylinder (astropy's Sun, geocentric).
        along = np.einsum("it,it->t", r_geo, v["sun"])
        perp = np.linalg.norm(r_geo - along * v["sun"], axis=0)
        lit = (along > 0) | (perp > 6378.137)
        unsure = (along <= 0) & (np.abs(perp - 6371.0) < 60.0)
        return fx, fy, np.where(unsure, None, lit), cz > 0.5


def _aberrate(u_dir, beta):
    """First-order aberration of unit vectors (3, n) by velocities beta = v / c (3, n)."""
    out = u_dir + beta - np.einsum("it,it->t", u_dir, beta) * u_dir
    return out / np.linalg.norm(out, axis=0)


def ccds_crossed(fx, fy, lit, front, shut, sub=400):
    """CCDs the sunlit track crosses: each chord between samples (straight in the gnomonic
    plane; none while the shutter is closed, ``shut[k]`` for the chord from sample k) cut into
    ``sub`` pieces, through the distortion to mm, each piece clipped by every CCD box. Returns
    the set of names and the track's length on the CCDs (mm); (None, None) when sunlight is
    unsure (or changes) on a chord that reaches the field."""
    names, length = set(), 0.0
    for k in range(len(fx) - 1):
        if shut[k] or not (front[k] and front[k + 1]):
            continue
        f = np.linspace(0.0, 1.0, sub + 1)
        x = fx[k] + f * (fx[k + 1] - fx[k])
        y = fy[k] + f * (fy[k + 1] - fy[k])
        if np.hypot(x, y).min() > math.radians(2.2):
            continue
        if lit[k] is None or lit[k + 1] is None or lit[k] != lit[k + 1]:
            return None, None
        if not lit[k]:
            continue
        theta = np.hypot(x, y)
        scale = radius_mm(theta) / np.where(theta > 0, theta, 1.0)
        xm, ym = x * scale, y * scale
        inside = clipped_lengths(xm[:-1], ym[:-1], xm[1:], ym[1:])
        names |= {BOX_NAMES[b] for b in np.flatnonzero(inside.sum(axis=0) > 0)}
        length += float(inside.sum())
    return names, length


# --- crossings against skyfield -------------------------------------------------------------

#: The shell of the comparison: 1000 satellites at 550 km, and its epoch (UTC).
SHELL = {"planes": 40, "per_plane": 25, "phasing": 1, "height": 550.0, "inclination": 53.0}
EPOCH = "2026-06-15T23:00:00"
#: Four visits in the evening twilight of 2026-06-15 at Rubin: (UTC start, band, rotSkyPos,
#: snaps); two snaps of 15 s leave the readout from 15 to 17 s without a streak.
AIMED = (("2026-06-15T23:12:00", "g", 0.0, 1), ("2026-06-15T23:27:30", "r", 37.0, 1),
         ("2026-06-15T23:41:10", "i", 250.0, 1), ("2026-06-15T23:20:00", "z", 120.0, 2))


@pytest.fixture(scope="module")
def skyfield_night(tmp_path_factory):
    """A 1000-satellite shell as a TLE file, three visits each aimed (by skyfield) at one of
    its sunlit satellites, ``inject survey`` run on them, and the skyfield reference."""
    from astropy.time import Time
    from skyfield.api import EarthSatellite

    from inject.cli.main import main
    from inject.orbits.passes import walker_shell

    folder = tmp_path_factory.mktemp("skyfield")
    orbits = walker_shell(SHELL["planes"] * SHELL["per_plane"], SHELL["planes"],
                          SHELL["phasing"], SHELL["height"], SHELL["inclination"], EPOCH)
    lines = [(f"T{n:04d}", *orbit.tle_lines()) for n, orbit in enumerate(orbits)]
    with open(folder / "shell.tle", "w") as stream:
        stream.write("".join(f"{a}\n{b}\n{c}\n" for a, b, c in lines))
    ref = Skyfield()
    sats = [EarthSatellite(b, c, a, ref.ts) for a, b, c in lines]
    rows, aimed = [], []
    for k, (start, band, rotation, snaps) in enumerate(AIMED):
        mjd = Time(start, scale="utc").tai.mjd
        t_mid = ref.ts.tai_jd(mjd + 2400000.5 + 15.0 / 86400.0)
        sun = ref.visit(mjd + 15.0 / 86400.0, 0.0, 0.0, 0.0, 0.0)["sun"][:, 0]
        best = None
        for n, sat in enumerate(sats):  # the highest above 30 deg, clearly sunlit, mid-exposure
            topo = (sat - ref.site).at(t_mid)
            alt = topo.altaz()[0].degrees
            if alt > (best[0] if best else 30.0):
                r = sat.at(t_mid).position.km
                along = r @ sun
                if along > 0 or np.linalg.norm(r - along * sun) > 6500.0:
                    best = (alt, topo, n)
        ra, dec, _ = best[1].radec()
        aimed.append(best[2])
        rows.append({"observationId": 100 + k, "observationStartMJD": mjd,
                     "fieldRA": ra._degrees, "fieldDec": dec.degrees, "rotSkyPos": rotation,
                     "band": band, "visitExposureTime": 30.0, "numExposures": snaps,
                     "seeingFwhmEff": 0.8})
    db = write_opsim(str(folder / "night.db"), rows)
    const = write_constellation(str(folder), "tle: shell.tle\n")
    out = folder / "out"
    assert main(["survey", db, "-o", str(out), "--constellation", const]) == 0
    reference, tracks = {}, []
    for row, n_aimed in zip(rows, aimed):
        snaps = row["numExposures"]
        v = ref.visit(row["observationStartMJD"], 30.0 + 2.0 * (snaps - 1), row["fieldRA"],
                      row["fieldDec"], row["rotSkyPos"])
        # The readouts between the snaps, 2 s after each 30 / snaps s exposure.
        readout = [(k * (30.0 / snaps + 2.0) - 2.0, k * (30.0 / snaps + 2.0))
                   for k in range(1, snaps)]
        mid = 0.5 * (v["t_s"][1:] + v["t_s"][:-1])
        dark = np.array([any(a < m < b for a, b in readout) for m in mid], bool)
        for n, ((name, _, _), sat) in enumerate(zip(lines, sats)):
            fx, fy, lit, front = ref.track(sat, v)
            names, length = ccds_crossed(fx, fy, lit, front, dark)
            if names is None or names:
                reference[row["observationId"], name] = (names, length)
            if n == n_aimed:
                tracks.append((row, lines[n], fx, fy))
    return {"streaks": read_csv(out / "streaks.csv"), "reference": reference,
            "tracks": tracks, "visits": read_csv(out / "visits.csv")}


def test_field_angles_agree_with_skyfield(skyfield_night):
    """The aimed satellites' apparent positions (inject.orbits.passes.compute_pass, every
    second) against skyfield's, within 0.2" (1 px): the frames, UT1, polar motion, light time
    and aberration agree."""
    from astropy.time import Time

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import Exposure, Orbit, compute_pass

    for row, (name, line1, line2), fx, fy in skyfield_night["tracks"]:
        p = compute_pass(Orbit.from_tle(line1, line2, name),
                         Exposure(Time(row["observationStartMJD"], format="mjd", scale="tai"),
                                  30.0),
                         Pointing(row["fieldRA"], row["fieldDec"], row["rotSkyPos"]),
                         t_s=np.arange(len(fx), dtype=float))
        gap = np.hypot(np.radians(p.field_x_deg) - fx, np.radians(p.field_y_deg) - fy)
        assert np.degrees(gap).max() * 3600.0 < 0.2


def test_every_crossing_agrees_with_skyfield_to_the_ccd(skyfield_night):
    streaks, reference = skyfield_night["streaks"], skyfield_night["reference"]
    planned = {(int(r["observationId"]), r["satellite"]): set(r["ccds"].split())
               for r in streaks}
    unsure = {key for key, (names, _) in reference.items() if names is None}
    assert len(unsure) <= 1, unsure  # a satellite entering the shadow inside the field
    expected = {key: names for key, (names, _) in reference.items() if names}
    assert len(expected) >= 3  # the three aimed satellites at least
    for key in set(planned) | set(expected):
        if key in unsure:
            continue
        assert planned.get(key) == expected.get(key), key
    # The two-snap visit's satellite is at the boresight during the readout: two parts.
    assert [r["sunlit_parts"] for r in streaks if r["observationId"] == "103"] == ["2"]


def test_streak_length_and_pixels_follow_the_independent_track(skyfield_night):
    """The length on the CCDs is skyfield's to 0.3%, and the pixels lost are that length
    (in 10 um pixels) times the mask width, plus at most the end caps."""
    streaks, reference = skyfield_night["streaks"], skyfield_night["reference"]
    for row in streaks:
        names, length_mm = reference[int(row["observationId"]), row["satellite"]]
        if names is None:
            continue
        length_px = length_mm / 0.010
        length_deg = length_mm * PLATE / 3600.0
        assert float(row["length_deg"]) == pytest.approx(length_deg, rel=3e-3)
        width = float(row["mask_width_px"])
        lost = int(row["pixels_lost"])
        assert length_px * width * 0.99 <= lost <= (length_px + 2 * width) * width * 1.01


def test_a_visits_streak_length_is_skyfields_tracks_on_the_ccds(skyfield_night):
    """visits.csv's streak_length_deg: the sum over the visit's satellites of skyfield's
    sunlit track on the science CCDs (the gaps excluded), to 0.3%; 0 where none crosses. A
    visit with a satellite entering the shadow in the field (skyfield's track unsure) is left
    out."""
    totals, unsure = {}, set()
    for (vid, _), (names, length_mm) in skyfield_night["reference"].items():
        if names is None:
            unsure.add(vid)
        elif names:
            totals[vid] = totals.get(vid, 0.0) + length_mm * PLATE / 3600.0
    visits = skyfield_night["visits"]
    assert len(set(totals) - unsure) >= 3 and len(visits) == len(AIMED)
    for row in visits:
        if int(row["observationId"]) in unsure:
            continue
        expected = totals.get(int(row["observationId"]), 0.0)
        assert float(row["streak_length_deg"]) == pytest.approx(expected, rel=3e-3, abs=1e-12)


# --- pixels lost: closed forms --------------------------------------------------------------

#: R22_S11 (e2v, at the focal plane's centre: pixel (2047.5, 2001.5) at (0, 0) mm) and its
#: neighbour R22_S12 (42.25 mm along x), 0.01 mm pixels.
S11, S12 = fp.ccd("R22_S11"), fp.ccd("R22_S12")


def _mm(px):
    """Focal-plane mm of an R22_S11 pixel coordinate along x (or y, with 2001.5)."""
    return (px - 2047.5) * 0.010


def _lost(xs_mm, ys_mm, width, ccds=(S11,)):
    return sum(union_pixels(run_spans(xs_mm, ys_mm, width, c)) for c in ccds)


def test_a_chord_across_a_ccd_loses_its_length_times_the_width():
    # y = 2001.8 px: the 20 px mask holds rows 1992-2011; the line runs past both ends of the
    # 4096-pixel rows.
    y = (2001.8 - 2001.5) * 0.010
    assert _lost([-30.0, 30.0], [y, y], 20.0) == 4096 * 20


def test_a_chord_ending_on_the_ccd_adds_its_end_caps():
    # From x = 1000.25 to 3000.25 px with three vertices: 2000 px long, plus the caps of half
    # the width at each end (none at the inner vertex): (2000 + 20) x 20.
    y = (2001.8 - 2001.5) * 0.010
    xs = [_mm(1000.25), _mm(2000.25), _mm(3000.25)]
    assert _lost(xs, [y] * 3, 20.0) == (2000 + 20) * 20


def test_a_chord_over_a_gap_counts_only_the_ccds():
    # From pixel x 2047.75 of R22_S11 to pixel x 2047.75 of R22_S12 (1.29 mm of gap between
    # them): on S11 from the start's cap (2037.75) to its edge (4095.5), on S12 from its edge
    # (-0.5) to the end's cap (2057.75): (2057.75 + 2058.25) x 20; the gap's 129 px are lost
    # light, not pixels.
    y = (2001.8 - 2001.5) * 0.010
    lost = _lost([0.0025, 42.2525], [y, y], 20.0, (S11, S12))
    assert lost == (2057.75 + 2058.25) * 20


def test_overlapping_streaks_count_their_pixels_once():
    # A row streak (rows 1992-2011, all 4096 columns) and a column streak (columns 991-1010,
    # all 4004 rows) cross in a 20 x 20 square: 4096 x 20 + 4004 x 20 - 20 x 20.
    y = (2001.8 - 2001.5) * 0.010
    x = _mm(1000.3)
    row = run_spans([-30.0, 30.0], [y, y], 20.0, S11)
    column = run_spans([x, x], [-30.0, 30.0], 20.0, S11)
    assert union_pixels(row) + union_pixels(column) == 4096 * 20 + 4004 * 20
    assert union_pixels(row + column) == 4096 * 20 + 4004 * 20 - 20 * 20


def test_mask_width_is_the_simulators_streak_plane_width():
    """The masker's sb rule on the model (out to 1 sky sigma, at least the FWHM) against the
    STREAK plane of a rendered CCD (the model's pixels above the same level): a column across
    a horizontal streak holds as many flagged pixels as the width, within a pixel."""
    import inject
    from inject.maskplanes import MASK_PLANES
    from inject.profile import Seeing
    from inject.satellite import Box
    from inject.streak import StreakModel
    from inject.survey.plan import mask_width_px

    for mag, band in ((5.0, "g"), (9.0, "r")):
        scene = inject.parse_scene(inject.apply_overrides(inject.DEFAULT_SCENE, [
            "detector.nx=160", "detector.ny=160", "stars=false", f"band={band}",
            "satellites.0.track.x0=-50", "satellites.0.track.y0=80.3",
            "satellites.0.track.angle=0", f"satellites.0.mag={mag}"]))
        result = inject.simulate(scene)
        flagged = (result.mask & (1 << MASK_PLANES["STREAK"])) > 0
        across = flagged[:, 60:100].sum(axis=0)
        sat = scene.satellites[0]
        model = StreakModel(height_km=sat.height, zenith_deg=scene.zenith, phi_deg=sat.phi,
                            shape=Box(7.25, 2.65), mag=mag, band_name=band,
                            seeing=Seeing(scene.seeing))
        width = mask_width_px(model, result.noise_sigma)
        assert np.all(np.abs(across - width) <= 1.0), (mag, across, width)


# --- visits -----------------------------------------------------------------------------------

def _row(k=0, **changes):
    row = {"observationId": k, "observationStartMJD": 61206.97 + k * 0.001, "fieldRA": 150.0,
           "fieldDec": -30.0, "rotSkyPos": 10.0, "band": "r", "visitExposureTime": 30.0,
           "numExposures": 1, "seeingFwhmEff": 0.9}
    return {**row, **changes}


def test_visits_from_sqlite_and_csv_are_the_same(tmp_path):
    from inject.survey.visits import read_visits

    rows = [_row(2, band="g"), _row(1, filter="r_57"), _row(0, numExposures=2)]
    columns = [c if c != "band" else "filter" for c in COLUMNS]
    for row in rows:
        row["filter"] = row.pop("band") if "filter" not in row else row.pop("filter")
        row.pop("band", None)
    db = read_visits(write_opsim(str(tmp_path / "n.db"), rows, columns))
    with open(tmp_path / "n.csv", "w", newline="") as stream:
        writer = csv.DictWriter(stream, columns)
        writer.writeheader()
        writer.writerows(rows)
    assert read_visits(tmp_path / "n.csv") == db
    assert [v.observation_id for v in db] == [0, 1, 2]  # in start order
    assert [v.band for v in db] == ["r", "r", "g"]  # 'r_57', a physical filter: band r


def test_the_start_is_tai_and_the_snaps_leave_the_readout_out():
    from inject.survey.plan import visit_times
    from inject.survey.visits import Visit

    # MJD 61206.5 TAI is 2026-06-15 12:00:00 TAI, 37 s (TAI - UTC since 2017) before in UTC.
    visit = Visit(1, 61206.5, 0.0, 0.0, 0.0, "r", 30.0, n_exposures=2, seeing_fwhm_eff=1.0)
    assert visit.start.utc.isot == "2026-06-15T11:59:23.000"
    assert visit.snaps() == ((0.0, 15.0), (17.0, 15.0))
    t = visit_times(visit)
    assert t.min() == 0.0 and t.max() == 32.0
    assert not np.any((t > 15.0 + 1e-9) & (t < 17.0 - 1e-9))
    # FWHMgeom = 0.822 FWHMeff + 0.052 (SMTN-002).
    assert visit.seeing_arcsec == pytest.approx(0.874)


def test_job_slices_take_every_njobs_th_visit(tmp_path):
    from inject.survey.visits import read_visits, select_visits

    visits = read_visits(write_opsim(str(tmp_path / "n.db"), [_row(k) for k in range(7)]))
    assert [v.observation_id for v in select_visits(visits, 1, 3)] == [1, 4]
    assert select_visits(visits) == visits


# --- one-line errors, nothing written ---------------------------------------------------------

def _survey(cli, tmp_path, db, const, *extra):
    out = tmp_path / "out"
    status, _, err = cli("survey", db, "-o", out, "--constellation", const, *extra, strict=True)
    return status, err, out


def _shell_file(tmp_path, shell="{height: 550, inclination: 53, planes: 2, per_plane: 2, "
                               "phasing: 1}"):
    return write_constellation(str(tmp_path), f"epoch: {EPOCH}\nshells:\n  - {shell}\n")


@pytest.mark.parametrize("make, words", [
    (lambda p: (p.write_text("not a database\n"), p)[1], "neither a SQLite database nor a .csv"),
    (lambda p: write_opsim(str(p), [_row()], table="visits"), "no 'observations' table"),
    (lambda p: write_opsim(str(p), [_row()], [c for c in COLUMNS if c != "rotSkyPos"]),
     "no column rotSkyPos"),
    (lambda p: write_opsim(str(p), []), "holds no visit (an empty night)"),
    (lambda p: write_opsim(str(p), [_row(band="w")]), "not an LSST band"),
])
def test_a_bad_database_is_one_line_and_writes_nothing(cli, tmp_path, make, words):
    db = make(tmp_path / "night.db")
    status, err, out = _survey(cli, tmp_path, db, _shell_file(tmp_path))
    assert status == 2 and words in err
    assert not out.exists()


@pytest.mark.parametrize("shell, words", [
    ("{height: 100, inclination: 53, planes: 2, per_plane: 2, phasing: 1}", "below 150 km"),
    ("{height: -5, inclination: 53, planes: 2, per_plane: 2, phasing: 1}", "below 150 km"),
    ("{height: 550, inclination: 53, planes: 0, per_plane: 2, phasing: 0}", "at least one"),
    ("{height: 550, inclination: 53, planes: 3, per_plane: 0, phasing: 0}", "at least one"),
    ("{height: 550, inclination: 53, planes: 3, per_plane: 2, phasing: 3}", "0 .. planes - 1"),
    ("{height: 550, inclination: 200, planes: 3, per_plane: 2, phasing: 1}", "inclination"),
    ("{height: 550, planes: 3, per_plane: 2, phasing: 1}", "missing keys ['inclination']"),
])
def test_a_shell_that_cannot_exist_is_one_line(cli, tmp_path, shell, words):
    db = write_opsim(str(tmp_path / "night.db"), [_row()])
    status, err, out = _survey(cli, tmp_path, db, _shell_file(tmp_path, shell))
    assert status == 2 and words in err and "shells[0]" in err
    assert not out.exists()


def test_outputs_appear_together_and_are_not_replaced(cli, tmp_path, digest):
    db = write_opsim(str(tmp_path / "night.db"), [_row(0), _row(1)])
    const = _shell_file(tmp_path)
    status, _, out = _survey(cli, tmp_path, db, const, "--no-plots")
    assert status == 0
    assert sorted(os.listdir(out)) == ["nights", "streaks.csv", "summary.json",
                                       "survey_claim.json", "visits.csv"]
    before = digest(out / "visits.csv")
    status, err, _ = _survey(cli, tmp_path, db, const, "--no-plots")
    assert status == 2 and "exists" in err and digest(out / "visits.csv") == before
    visits = read_csv(out / "visits.csv")
    assert [v["observationId"] for v in visits] == ["0", "1"]
    assert [v["n_streaks"] for v in visits] == ["0", "0"]


# --- the night's prefilter ------------------------------------------------------------------

#: A 350 km shell (the lowest, nearest satellites: the prefilter's largest errors) and a 550 km
#: one, 300 satellites.
LOW = {"planes": 10, "per_plane": 15, "phasing": 1, "height": 350.0, "inclination": 53.0}
HIGH = {"planes": 10, "per_plane": 15, "phasing": 3, "height": 550.0, "inclination": 97.6}
#: Offsets (deg) of the boresights from an aimed satellite: its track passes at most that far
#: from the boresight, many near the field's 2.1 deg edge.
OFFSETS = (0.0, 1.0, 1.9, 2.0, 2.05, 2.1, 2.12, 2.15, 2.2, 2.3, 2.6, 4.0)


@pytest.fixture(scope="module")
def prefilter_night():
    """Twelve visits through a night, each aimed at the highest satellite when one is above
    30 deg (astropy's frames, not the prefilter's) and moved off its track by
    :data:`OFFSETS`; one of two snaps."""
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import RUBIN, FieldFrame, propagate_teme, walker_shell
    from inject.survey.visits import Visit

    epoch = Time("2026-06-15T22:00:00", scale="utc")
    orbits = [o for k, s in enumerate((LOW, HIGH)) for o in walker_shell(
        s["planes"] * s["per_plane"], s["planes"], s["phasing"], s["height"],
        s["inclination"], epoch, raan0_deg=17.0 * k, name=f"s{k}")]
    visits, start = [], epoch
    for k, offset in enumerate(OFFSETS):
        while True:  # the next minute with a satellite above 30 deg
            start = start + 60 * u.s
            mid = start + 15 * u.s
            times = Time([mid, mid + 1 * u.s])
            frame = FieldFrame.build(times, Pointing(0.0, 0.0), RUBIN)
            r, _ = propagate_teme(orbits, times)
            _, _, alt, az = frame.to_altaz(np.einsum("tij,stj->sti", frame.teme_to_itrs, r))
            n = int(np.argmax(alt[:, 0]))
            if alt[n, 0] > 30.0:
                break
        sky = SkyCoord(az=az[n] * u.deg, alt=alt[n] * u.deg,
                       frame=AltAz(obstime=times, location=RUBIN.location)).icrs
        # Off the track, square to its motion: the track passes about ``offset`` away.
        aim = sky[0].directional_offset_by(sky[0].position_angle(sky[1]) + 90 * u.deg,
                                           offset * u.deg)
        visits.append(Visit(k, start.tai.mjd, aim.ra.deg, aim.dec.deg, 20.0 * k, "r", 30.0,
                            n_exposures=2 if k == 5 else 1))
        start = start + 900 * u.s
    return orbits, visits


def _exact_closest(p):
    """The closest approach (deg, gnomonic) of an exact pass's apparent track above the
    horizon to the boresight: its samples and the chords between them."""
    from inject.orbits.passes import segment_distances

    xi, eta = p.xi_deg, p.eta_deg
    ok = np.isfinite(xi) & np.isfinite(eta) & (p.apparent_alt_deg > 0)
    point = np.where(ok, np.hypot(np.nan_to_num(xi), np.nan_to_num(eta)), np.inf).min()
    seg = np.where(ok[:-1] & ok[1:], segment_distances(np.nan_to_num(xi),
                                                        np.nan_to_num(eta)), np.inf)
    return min(point, seg.min())


def test_the_night_prefilter_keeps_every_satellite_an_exact_pass_puts_in_the_field(
        prefilter_night):
    """Every satellite of every visit through exact passes (no prefilter: SGP4 at every
    second, astropy's frames, light time, aberration): each one whose track enters the
    2.1 deg field is a candidate of :class:`NightPrefilter`, and for every satellite within
    10 deg the prefilter's closest approach is within half its margin of the exact one (the
    margin is twice the error bound of the module notes). No satellite its umbra test calls
    dark has a sunlit sample (the penumbra included) in the exact pass."""
    from astropy import units as u

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import Exposure, FieldFrame, compute_pass
    from inject.survey.plan import visit_times
    from inject.survey.prefilter import NightPrefilter, prefilter_margin_deg

    orbits, visits = prefilter_night
    night = NightPrefilter(orbits, visits)
    # The lowest shell sets the margin: 0.104 deg at 350 km (0.065 at 550).
    assert night.margin_deg == pytest.approx(prefilter_margin_deg(350.0), rel=0.02)
    assert 0.09 < night.margin_deg < 0.12
    in_field, near, worst = 0, 0, 0.0
    edge = n_dark = n_lit = 0
    for visit in visits:
        end = float(visit_times(visit)[-1])
        ts = np.linspace(0.0, end, int(end) + 1)
        pointing = Pointing(visit.ra_deg, visit.dec_deg, visit.rotation_deg)
        exposure = Exposure(visit.start, end)
        frame = FieldFrame.build(visit.start + ts * u.s, pointing)
        passes = [compute_pass(o, exposure, pointing, t_s=ts, frame=frame, check_epoch=False)
                  for o in orbits]
        exact = np.array([_exact_closest(p) for p in passes])
        lit = np.array([p.sun_fraction.max() > 0 for p in passes])
        kept = set(night.candidates(visit).tolist())
        entered = set(np.flatnonzero(exact <= 2.1).tolist())
        assert entered <= kept, (visit.observation_id, entered - kept)
        # The umbra test: a satellite it calls dark has no sunlit sample in the exact pass.
        k = night._index[visit.observation_id]
        dark = night._dark(k, night.positions(night._samples[k])[0])
        assert not (dark & lit).any()
        n_dark += int(dark.sum())
        n_lit += int(lit.sum())
        assert entered & set(np.flatnonzero(lit).tolist()) <= set(
            night.candidates(visit, sunlit=True).tolist())
        close = np.flatnonzero(exact < 10.0)
        mine = night.closest_deg(visit, close)
        worst = max(worst, float(np.max(np.abs(mine - exact[close]), initial=0.0)))
        in_field += len(entered)
        near += len(close)
        edge += int(np.sum(np.abs(exact - 2.1) < 0.2))
    print(f"worst {worst:.4f} deg, in field {in_field}, within 10 deg {near}, "
          f"within 0.2 deg of the edge {edge}, dark {n_dark}, sunlit {n_lit}")
    assert worst < 0.5 * night.margin_deg  # measured 0.0144 deg (margin 0.104)
    assert in_field >= 4 and near >= 12 and edge >= 6  # the edge is exercised (5, 13, 7)
    assert n_dark > 500 and n_lit > 500  # both sides of the shadow (1058 and 2534 of 3600)


def test_the_night_grid_interpolates_sgp4_within_its_bound(prefilter_night):
    """The Hermite interpolation between the 300 s nodes against SGP4 itself at odd times:
    within ``step^4 / 384 n^4 a`` of a circular Kepler orbit (0.24 km at 350 km, 0.13 km at
    550) and 5% for the Earth's flattening (measured 0.8% over it at 350 km)."""
    from astropy.time import Time

    from inject.orbits.passes import propagate_teme
    from inject.survey.prefilter import MU_KM3_S2, R_EQ_KM, NightPrefilter

    orbits, visits = prefilter_night
    night = NightPrefilter(orbits, visits)
    t_s = np.array([17.0, 151.3, 299.9, 1234.5, 4000.0])
    r, v = night.positions(t_s)
    times = Time(np.full(t_s.size, night._jd1), night._jd2 + t_s / 86400.0, format="jd",
                 scale="utc")
    r_ref, v_ref = propagate_teme(orbits, times)
    err = np.linalg.norm(r - r_ref, axis=-1).max(axis=1)
    for lo, hi, height in ((0, 150, 350.0), (150, 300, 550.0)):
        a = R_EQ_KM + height
        bound = 300.0 ** 4 / 384.0 * (MU_KM3_S2 / a ** 3) ** 2 * a
        assert err[lo:hi].max() < 1.05 * bound
        assert err[lo:hi].max() > 0.1 * bound  # the bound is not loose by more than 10x
    assert np.abs(v - v_ref).max() < 0.01  # km/s


#: Satellites of the varied night: Walker shells (height km, inclination deg, planes x per
#: plane) at the constellation's lowest perigee and highest orbit, polar and retrograde.
VARIED_SHELLS = ((340.0, 53.0, 8, 12), (1200.0, 88.0, 8, 12), (600.0, 140.0, 6, 12))
#: Visits of the varied night, each aimed at a satellite put at (alt, az) deg (height km,
#: inclination deg) at its middle, minutes after 22:40 UTC, moved off its track by offset
#: deg: low (20 deg) and at the zenith, in the evening's twilight.
VARIED_VISITS = ((20.0, 200.0, 340.0, 53.0, 0.0, 0), (89.0, 30.0, 340.0, 97.6, 2.1, 6),
                 (20.0, 100.0, 1200.0, 88.0, 2.15, 13), (89.5, 300.0, 1200.0, 140.0, 0.5, 21),
                 (45.0, 0.0, 550.0, 70.0, 1.9, 34), (25.0, 270.0, 340.0, 140.0, 2.05, 47),
                 (85.0, 150.0, 600.0, 53.0, 2.3, 58), (30.0, 60.0, 340.0, 53.0, 2.0, 71))


def _tle_with_drag(satnum, epoch, days_old, perigee_km, e, inclination, raan, argp, ma,
                   bstar):
    """An SGP4 element set with drag (``bstar``, 1/earth radii), eccentricity ``e``, its
    epoch ``days_old`` days before ``epoch``."""
    from sgp4.api import WGS72, Satrec

    from inject.orbits.passes import Orbit

    a_er = (6378.135 + perigee_km) / (1.0 - e) / 6378.135
    no_kozai = 60.0 / math.sqrt(6378.135 ** 3 / 398600.8) / a_er ** 1.5  # rad/min
    sat = Satrec()
    sat.sgp4init(WGS72, "i", satnum, epoch.utc.jd - 2433281.5 - days_old, bstar, 0.0, 0.0, e,
                 math.radians(argp), math.radians(inclination), math.radians(ma), no_kozai,
                 math.radians(raan))
    return Orbit(sat, name=f"old-{satnum}")


@pytest.fixture(scope="module")
def varied_night():
    """360 satellites (the shells of :data:`VARIED_SHELLS`, 96 element sets with drag up to
    60 days old, e up to 0.02, polar and retrograde, perigees 340-700 km) and the 8 aimed
    ones of :data:`VARIED_VISITS`, with those visits (one of two snaps)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, SkyCoord
    from astropy.time import Time

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import RUBIN, FieldFrame, Orbit, aimed_orbit, walker_shell
    from inject.survey.visits import Visit

    epoch = Time("2026-06-15T22:40:00", scale="utc")
    orbits = [o for k, (height, inc, planes, per) in enumerate(VARIED_SHELLS)
              for o in walker_shell(planes * per, planes, 1, height, inc, epoch - 2 * u.day,
                                    raan0_deg=40.0 * k, name=f"v{k}")]
    rng = np.random.default_rng(7)
    for n in range(96):
        orbits.append(_tle_with_drag(
            70000 + n, epoch, rng.uniform(0.0, 60.0), rng.uniform(340.0, 700.0),
            rng.uniform(0.0, 0.02), rng.choice([53.0, 70.0, 90.0, 97.6, 120.0]),
            rng.uniform(0, 360), rng.uniform(0, 360), rng.uniform(0, 360),
            rng.uniform(1e-5, 3e-4)))
    visits = []
    for k, (alt, az, height, inc, offset, minutes) in enumerate(VARIED_VISITS):
        mid = epoch + (minutes * 60 + 15) * u.s
        tle = aimed_orbit(mid, alt, az, height_km=height, inclination_deg=inc,
                          ascending=k % 2 == 0, name=f"aim-{k}", satnum=80000 + k)
        orbits.append(Orbit.from_tle(*tle.tle_lines(), name=f"aim-{k}"))
        times = Time([mid, mid + 1 * u.s])
        frame = FieldFrame.build(times, Pointing(0.0, 0.0), RUBIN)
        from inject.orbits.passes import propagate_teme

        r, _ = propagate_teme([orbits[-1]], times)
        _, _, alt_now, az_now = frame.to_altaz(np.einsum("tij,stj->sti", frame.teme_to_itrs, r))
        sky = SkyCoord(az=az_now[0] * u.deg, alt=alt_now[0] * u.deg,
                       frame=AltAz(obstime=times, location=RUBIN.location)).icrs
        aim = sky[0].directional_offset_by(sky[0].position_angle(sky[1]) + 90 * u.deg,
                                           offset * u.deg)
        visits.append(Visit(k, (mid - 15 * u.s).tai.mjd, aim.ra.deg, aim.dec.deg, 30.0 * k,
                            "r", 30.0, n_exposures=2 if k == 3 else 1))
    return orbits, visits


def _every_satellite_candidates(night, visit, sunlit):
    """The candidates of ``visit`` by tests 1 and 2 of :mod:`inject.survey.prefilter`'s notes
    on every satellite, propagated at every node (no shortlist), and test 1's survivors."""
    k = night._index[visit.observation_id]
    ts, site, b = night._samples[k], night._site[k], night._b[k]
    r, v = night.positions([0.5 * (ts[0] + ts[-1])])
    los = r[:, 0] - site.mean(axis=0)
    z = los @ b
    d = np.linalg.norm(los - z[:, None] * b, axis=1)
    reach = (1.02 * np.linalg.norm(v[:, 0], axis=1) + 0.47) * 0.5 * (ts[-1] - ts[0])
    radius = math.radians(night.radius)
    near = np.flatnonzero((d <= z * math.tan(radius) + (reach + 0.1) / math.cos(radius))
                          & (z >= -(reach + 0.1)))
    keep = night.closest_deg(visit, near) <= night.radius
    if sunlit:
        keep &= ~night._dark(k, night.positions(ts, near)[0])
    return near[keep], near


def test_the_shortlists_keep_every_candidate_on_a_varied_night(varied_night):
    """On 368 satellites (340 to 1200 km, polar and retrograde, eccentric element sets with
    drag up to 60 days old) and 8 visits at 20 to 89.5 deg in twilight: the candidates (with
    the satellites propagated at the nodes only when a visit's shortlist keeps them) are
    those of every satellite propagated at every node, and hold every satellite whose exact
    pass enters the field (sunlit or not); the shortlist holds every satellite test 1 keeps;
    and fewer satellites than all are propagated at the nodes."""
    from astropy import units as u

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import Exposure, FieldFrame, compute_pass
    from inject.survey.plan import visit_times
    from inject.survey.prefilter import NightPrefilter, _half_space

    orbits, visits = varied_night
    night, every = NightPrefilter(orbits, visits), NightPrefilter(orbits, visits)
    entered_all = edge = n_above = n_close = 0
    for visit in visits:
        for sunlit in (False, True):
            mine = night.candidates(visit, sunlit=sunlit)
            theirs, near = _every_satellite_candidates(every, visit, sunlit)
            assert np.array_equal(mine, theirs), (visit.observation_id, sunlit)
        k = night._index[visit.observation_id]
        short = night._shortlist(k)
        assert set(near.tolist()) <= set(short.tolist()), visit.observation_id
        # Test 0 keeps every satellite above its half-space (the coarse interpolation of all
        # satellites at test a's time; the regions of the interval's visits from the notes).
        kt = night._kt[k]
        coarse, (kept, _, _, t_c) = night._coarse(kt), night._interval(kt)
        group = night._groups[kt]
        backs = (coarse["slack"] + coarse["reach_speed"] * night._half[group] + 0.1
                 + coarse["speed"] * np.abs(night._mid[group] - t_c))
        cos_a = math.cos(math.radians(night.radius))
        n, level = _half_space(night._apex[group], night._b[group], backs, backs / cos_a,
                               math.tan(math.radians(night.radius)))
        above = np.flatnonzero(night._coarse_positions(coarse, t_c) @ n >= level)
        assert set(above.tolist()) <= set(kept.tolist())
        n_above += len(above)
        n_close += int(np.sum(np.abs(night._coarse_positions(coarse, t_c) @ n - level) < 50.0))
        end = float(visit_times(visit)[-1])
        t_s = np.linspace(0.0, end, int(end) + 1)
        pointing = Pointing(visit.ra_deg, visit.dec_deg, visit.rotation_deg)
        frame = FieldFrame.build(visit.start + t_s * u.s, pointing)
        exact = np.array([_exact_closest(compute_pass(
            o, Exposure(visit.start, end), pointing, t_s=t_s, frame=frame, check_epoch=False))
            for o in orbits])
        entered = set(np.flatnonzero(exact <= 2.1).tolist())
        assert entered <= set(night.candidates(visit).tolist()), visit.observation_id
        entered_all += len(entered)
        edge += int(np.sum(np.abs(exact - 2.1) < 0.2))
    fine = [node for k, node in night._nodes.items() if k not in night._coarse_nodes]
    done = sum(int(node[2].sum()) for node in fine)
    print(f"in field {entered_all}, within 0.2 deg of the edge {edge}, propagated at the "
          f"{len(fine)} nodes off the coarse grid {done} of {len(fine) * len(orbits)}, "
          f"above test 0's planes {n_above}, within 50 km of them {n_close}")
    assert n_close >= 3  # the planes' edge is exercised
    assert entered_all >= 5 and edge >= 5  # the edge is exercised (5, 5)
    assert len(fine) and done < 0.5 * len(fine) * len(orbits)


def test_the_half_space_of_test_0_holds_every_visits_region_and_no_more():
    """Test 0's half-space against points of the regions it must hold (``d <= z tan(a) +
    far``, ``z >= -back`` about each visit's line of sight), sampled on their boundaries
    (where ``r . n`` is least) for groups of visits 3 to 40 deg apart at 20 to 90 deg: every
    point is above the plane, and the lowest within 0.01 km of it (a shrunk bound fails)."""
    from inject.survey.prefilter import _half_space

    rng = np.random.default_rng(3)
    tan_a = math.tan(math.radians(2.2))
    lat = math.radians(-30.24)
    for trial in range(200):
        lon = rng.uniform(0.0, 2.0 * math.pi)
        up = np.array([math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon),
                       math.sin(lat)])
        east = np.cross([0.0, 0.0, 1.0], up)
        east /= np.linalg.norm(east)
        north = np.cross(up, east)
        m = int(rng.integers(1, 6))
        spread = math.radians(rng.uniform(3.0, 40.0))
        alt0, az0 = rng.uniform(math.radians(20.0), math.radians(90.0)), rng.uniform(0, 6.3)
        alt = np.clip(alt0 + rng.uniform(-spread, spread, m), math.radians(20.0), math.pi / 2)
        az = az0 + rng.uniform(-spread, spread, m)
        aims = (np.sin(alt)[:, None] * up + (np.cos(alt) * np.cos(az))[:, None] * north
                + (np.cos(alt) * np.sin(az))[:, None] * east)
        # The site turns by up to 140 km in a node interval.
        apexes = 6372.0 * up + rng.uniform(-70.0, 70.0, (m, 3))
        backs = rng.uniform(100.0, 2500.0, m)
        fars = backs / math.cos(math.atan(tan_a))
        n, level = _half_space(apexes, aims, backs, fars, tan_a)
        lowest = np.inf
        for apex, b, back, far in zip(apexes, aims, backs, fars):
            # The boundary points: z from -back up, |w| = z tan(a) + far, w toward every
            # direction square to b, and the one toward -n (the least r . n).
            e1 = np.cross(b, n if abs(b @ n) < 0.999999 else east)
            e1 /= np.linalg.norm(e1)
            e2 = np.cross(b, e1)
            z = np.concatenate([[-back], rng.uniform(-back, 3000.0, 200)])
            phi = rng.uniform(0.0, 2.0 * math.pi, z.size)
            w = (z * tan_a + far)[:, None] * (np.cos(phi)[:, None] * e1
                                              + np.sin(phi)[:, None] * e2)
            toward = n - (n @ b) * b
            if np.linalg.norm(toward) > 1e-9:
                w[0] = -(far - back * tan_a) * toward / np.linalg.norm(toward)
            points = apex + z[:, None] * b + w
            lowest = min(lowest, float((points @ n).min()) - level)
        assert lowest >= -1e-6, trial
        assert lowest < 0.01, (trial, lowest)


def test_the_boresights_and_the_sun_interpolated_through_the_night_are_astropys():
    """The boresights' and the Sun's directions in TEME, linear between astropy's at times
    up to 12 h apart, against astropy at each of 40 visits' middles over 11 h (all over the
    sky): the boresights within :data:`DIRECTION_ERROR_DEG` (0.01"; measured 0.001"), the
    Sun within 0.05" (measured 0.003"; the lunar wobble of the Earth bends its track by up to
    0.011" in 12 h, 0.5 m at 10,000 km, inside the umbra test's slack)."""
    from astropy import units as u
    from astropy.coordinates import TEME, SkyCoord, get_sun
    from astropy.time import Time

    from inject.orbits.passes import walker_shell
    from inject.survey.prefilter import DIRECTION_ERROR_DEG, NightPrefilter
    from inject.survey.visits import Visit

    epoch = Time("2026-06-15T22:00:00", scale="utc")
    orbits = walker_shell(4, 2, 1, 550.0, 53.0, epoch)
    rng = np.random.default_rng(11)
    visits = [Visit(k, (epoch + m * u.min).tai.mjd, ra, dec, 0.0, "r", 30.0)
              for k, (m, ra, dec) in enumerate(zip(np.sort(rng.uniform(0, 660, 40)),
                                                    rng.uniform(0, 360, 40),
                                                    rng.uniform(-89, 89, 40)))]
    night = NightPrefilter(orbits, visits)
    middles = Time(np.full(40, night._jd1), night._jd2 + night._mid / 86400.0, format="jd",
                   scale="utc")
    aim = SkyCoord([v.ra_deg for v in visits] * u.deg, [v.dec_deg for v in visits] * u.deg,
                   frame="icrs").transform_to(TEME(obstime=middles)).cartesian.xyz.value.T
    sun = get_sun(middles).transform_to(TEME(obstime=middles)).cartesian.xyz.value.T
    for mine, exact, bound in ((night._b, aim, DIRECTION_ERROR_DEG),
                               (night._sun, sun, 0.05 / 3600.0)):
        exact = exact / np.linalg.norm(exact, axis=1, keepdims=True)
        off = np.degrees(np.linalg.norm(mine - exact, axis=1))
        print(f"worst {off.max() * 3600:.2e} arcsec")
        assert off.max() < bound


def test_the_coarse_grid_interpolates_sgp4_within_its_bound(varied_night):
    """The coarse interpolation of the varied night's satellites (1800 s steps) against SGP4
    at odd times: within ``E_c`` (measured about a third of it: the bound is twice the
    Kepler orbit's), and SGP4's speed within the bound on it."""
    from astropy.time import Time

    from inject.orbits.passes import propagate_teme
    from inject.survey.prefilter import NightPrefilter

    orbits, visits = varied_night
    night = NightPrefilter(orbits, visits)
    worst = 0.0
    for kt in range(night._k_first, night._k_last):
        coarse = night._coarse(kt)
        t_s = (kt + np.array([0.13, 0.5, 0.91])) * night.node_step_s
        times = Time(np.full(t_s.size, night._jd1), night._jd2 + t_s / 86400.0, format="jd",
                     scale="utc")
        r_ref, v_ref = propagate_teme(orbits, times)
        for j, t in enumerate(t_s):
            err = np.linalg.norm(night._coarse_positions(coarse, t) - r_ref[:, j], axis=1)
            bound = coarse["slack"] - 0.5  # E_c + E_f
            assert err.max() < bound
            worst = max(worst, err.max() / bound)
        assert np.linalg.norm(v_ref, axis=-1).max() < coarse["speed"]
    print(f"worst error / bound {worst:.3f}")
    assert worst > 0.1  # not loose by more than 10x


def test_the_visit_frame_from_nodes_is_astropys_at_every_sample():
    """:func:`visit_frame` (astropy every 15 s, a polynomial between) against astropy at all
    301 samples of a 30 s visit and 321 of two snaps: directions within 1e-4" (measured
    2e-5"), the Sun within 0.05 km (12 m), the TEME -> ITRS rotation within 1e-9 (7 mm at
    7000 km)."""
    from astropy import units as u

    from inject.camera.wcs import Pointing
    from inject.orbits.passes import FieldFrame
    from inject.survey.plan import visit_frame, visit_times
    from inject.survey.visits import Visit

    for visit in (Visit(1, 61206.97, 150.0, -30.0, 10.0, "r", 30.0),
                  Visit(2, 61207.31, 300.0, 5.0, 200.0, "g", 30.0, n_exposures=2)):
        ts = visit_times(visit)
        pointing = Pointing(visit.ra_deg, visit.dec_deg, visit.rotation_deg)
        exact = FieldFrame.build(visit.start + ts * u.s, pointing)
        fast = visit_frame(visit.start, ts, pointing)
        for name in ("centre", "east", "north"):
            dev = np.linalg.norm(getattr(fast, name) - getattr(exact, name), axis=-1)
            assert np.degrees(dev.max()) * 3600 < 1e-4
        assert np.abs(fast.sun_itrs - exact.sun_itrs).max() < 0.05
        assert np.abs(fast.teme_to_itrs - exact.teme_to_itrs).max() < 1e-9
        assert np.abs(fast.to_icrs - exact.to_icrs).max() < 1e-8  # 1e-4" at 2.1 deg
        assert np.abs(fast.alt_deg - exact.alt_deg).max() * 3600 < 1e-3
        assert np.all(fast.t_from(visit.start.utc) == pytest.approx(ts, abs=1e-6))


def test_visits_planned_in_batches_are_each_visits_own_plan(prefilter_night, monkeypatch):
    """:func:`plan_visits` builds the frames of the visits with candidates together
    (:data:`FRAME_BATCH_VISITS` at a time, :meth:`FieldFrame.build_many`); in batches of
    three (of the four visits with candidates: one full, one short) every visit's row and
    streak rows are those of :func:`plan_visit` on its own, to the last digit, and one visit's
    frame from a batch is the one :func:`visit_frame` builds alone, bit for bit."""
    from dataclasses import replace

    from inject.errors import InputError
    from inject.orbits.passes import RUBIN
    from inject.survey import plan
    from inject.survey.constellation import parse_constellation
    from inject.survey.prefilter import NightPrefilter

    orbits, visits = prefilter_night
    raw = {"shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0,
           "epoch": "2026-06-15T22:00:00", "shells": [dict(LOW)]}
    constellation = replace(parse_constellation(raw), orbits=tuple(orbits))
    batches = []
    frames_at_nodes = plan._frames_at_nodes

    def counted(framed, site):
        batches.append(len(framed))
        return frames_at_nodes(framed, site)

    monkeypatch.setattr(plan, "FRAME_BATCH_VISITS", 3)
    monkeypatch.setattr(plan, "_frames_at_nodes", counted)
    together = plan.plan_visits(visits, constellation)
    prefilter = NightPrefilter(orbits, visits)
    alone = [plan.plan_visit(v, constellation, prefilter=prefilter) for v in visits]
    framed = [v for v, p in zip(visits, alone) if p.n_candidates]
    assert len(framed) == 4 and sum(len(p.streaks) for p in alone) >= 2
    assert batches == [3, 1]
    for a, b in zip(together, alone, strict=True):
        assert repr(a.visit_row()) == repr(b.visit_row())
        assert repr(a.streak_rows()) == repr(b.streak_rows())
    pointing, ts, exposure = plan._visit_setup(framed[-1])
    at_nodes = frames_at_nodes(framed[-3:], RUBIN)
    batch = plan.visit_frame(exposure.start, ts, pointing, at_nodes=at_nodes[-1])
    single = plan.visit_frame(exposure.start, ts, pointing)
    for name in ("centre", "east", "north", "alt_deg", "az_deg", "teme_to_itrs", "sun_itrs",
                 "to_icrs"):
        assert np.array_equal(getattr(batch, name), getattr(single, name)), name
    with pytest.raises(InputError, match="at_nodes"):  # another visit's
        plan.visit_frame(exposure.start, ts, pointing, at_nodes=at_nodes[0])


def test_the_constellation_may_ask_for_the_traced_pupil():
    from inject.errors import SceneError
    from inject.survey.constellation import parse_constellation
    from inject.survey.plan import _field

    raw = {"shape": {"type": "box", "length": 7.25, "width": 2.65}, "mag": 5.0,
           "shells": [dict(SHELL, planes=2, per_plane=2)]}
    raw["epoch"] = EPOCH
    assert parse_constellation(raw).pupil == "annulus"
    assert parse_constellation(dict(raw, pupil="rubin")).pupil == "rubin"
    with pytest.raises(SceneError, match="pupil='ideal'"):
        parse_constellation(dict(raw, pupil="ideal"))
    assert parse_constellation(raw).focus_offset_um == 0.0
    assert parse_constellation(dict(raw, pupil="rubin", focus_offset_um=-5)).focus_offset_um == -5
    with pytest.raises(SceneError, match=r"^constellation: focus_offset_um=5\.0: only with "
                                         r"pupil: rubin \(pupil: annulus"):
        parse_constellation(dict(raw, focus_offset_um=5))
    with pytest.raises(SceneError, match=r"focus_offset_um=2000.*\[-1000, 1000\]"):
        parse_constellation(dict(raw, pupil="rubin", focus_offset_um=2000))
    # Samples moving outward along the radius at 45 deg, then across it at x = 200 mm.
    t = np.linspace(50.0, 250.0, 21)
    out = _field(t, t, np.arange(21), 10)
    assert out["field_angle_deg"] == pytest.approx(
        math.degrees(math.hypot(*fp.field_angle(150.0, 150.0))), rel=1e-12)
    assert out["field_position_angle_deg"] == pytest.approx(0.0, abs=1e-9)
    y = np.linspace(-100.0, 100.0, 21)
    across = _field(np.full(21, 200.0), y, np.arange(21), 10)  # at (200, 0), moving +y
    assert across["field_position_angle_deg"] == pytest.approx(-90.0, abs=1e-9)
