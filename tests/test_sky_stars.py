"""Random stars are fixed to the sky: the same sky gives the same stars at any rotation, pointing
offset or CCD, and the counts per deg^2 follow the model."""
import math

import numpy as np
import pytest

from inject import Pointing, ccd_wcs, pointing_wcs, skytiles
from inject.camera import layout as fp
from inject.stars import sample_stars, star_field_spec

SPEC = star_field_spec({"mag_limit": 22.0, "galactic_l": 90.0, "galactic_b": 40.0})


def test_the_tiles_cover_the_sphere_once():
    """The tiles' exact solid angles add up to the whole sky, 4 pi sr."""
    total = sum(skytiles.tile_area_deg2((j, i)) for j in range(skytiles._N_BANDS)
                for i in range(skytiles._band_count(j)))
    assert total == pytest.approx(4 * math.pi * (180 / math.pi) ** 2, rel=1e-9)


def _stars(wcs, shape=(4000, 4072), seed=7, margin=100.0):
    return skytiles.sky_stars(SPEC, wcs, shape, margin, "g", seed, sample_stars)


@pytest.mark.parametrize("other", [Pointing(50.0, -30.0, 110.0),  # rotated 90 deg
                                   Pointing(50.1, -30.05, 20.0)])  # moved ~0.1 deg
def test_the_same_sky_gives_the_same_stars(other):
    """Each star seen under both pointings lands, under the second, where the second WCS puts
    its sky position under the first (to 0.01 px); most stars are seen under both."""
    ccd = fp.ccd("R22_S11")
    first, second = ccd_wcs(ccd, Pointing(50.0, -30.0, 20.0)), ccd_wcs(ccd, other)
    a, b = _stars(first), _stars(second)
    at = {m: (x, y) for m, x, y in zip(b["mag"], b["x"], b["y"])}  # magnitudes are unique
    common = [(x, y, m) for x, y, m in zip(a["x"], a["y"], a["mag"]) if m in at]
    assert len(common) > 0.5 * a["mag"].size > 50
    for x, y, m in common:
        ra, dec = first.pixel_to_world_values(x, y)
        xb, yb = second.world_to_pixel_values(ra, dec)
        assert math.hypot(xb - at[m][0], yb - at[m][1]) < 0.01


def test_two_ccds_share_the_stars_of_their_overlap():
    """Two neighbouring CCDs' grown areas overlap across the gap: a star in both is the same
    star at the same sky position."""
    pointing = Pointing(120.0, 10.0, 0.0)
    left, right = fp.ccd("R22_S11"), fp.ccd("R22_S12")
    wl, wr = ccd_wcs(left, pointing), ccd_wcs(right, pointing)
    a, b = _stars(wl), _stars(wr)
    shared = np.intersect1d(a["mag"], b["mag"])
    assert shared.size > 0
    for m in shared:
        ra_a, dec_a = wl.pixel_to_world_values(a["x"][a["mag"] == m][0], a["y"][a["mag"] == m][0])
        ra_b, dec_b = wr.pixel_to_world_values(b["x"][b["mag"] == m][0], b["y"][b["mag"] == m][0])
        assert float(ra_a) == pytest.approx(float(ra_b), abs=1e-9)
        assert float(dec_a) == pytest.approx(float(dec_b), abs=1e-9)


@pytest.mark.parametrize("pointing", [Pointing(50.0, -30.0, 20.0), Pointing(10.0, 89.95, 0.0),
                                      Pointing(10.0, -90.0, 0.0), Pointing(359.99, 0.0, 0.0)])
def test_counts_per_square_degree_follow_the_model(pointing):
    """Over 40 seeds, the stars on a 2000 x 2000 image average the model's density times its
    area (within 4 sigma), at the equator, at RA 0 and at and near the poles."""
    from inject.stars import _cumulative_counts_grid

    shape = (2000, 2000)
    wcs = pointing_wcs(pointing, shape, 0.2)
    expected = (2000 * 0.2 / 3600) ** 2 * _cumulative_counts_grid(SPEC)[1][-1]
    counts = [_stars(wcs, shape, seed, margin=0.0)["mag"].size for seed in range(40)]
    assert abs(np.mean(counts) - expected) < 4 * math.sqrt(expected / 40)


@pytest.mark.parametrize("name", ["R22_S12", "R41_S00"])
def test_a_cutouts_stars_are_placed_as_the_full_ccds_bit_for_bit(name):
    """Through a focal-plane CCD's WCS, whose SIP inverse iterates, a star is placed on its
    own: the stars a cut-out shares with its full CCD are at the same pixel positions, bit
    for bit (astropy's default inverse iterates until the worst point of the set converges,
    so the company moved every star of R22_S12's cut-out by ~3e-11 px)."""
    wcs = ccd_wcs(fp.ccd(name), Pointing(50.0, -30.0, 20.0))
    assert wcs.sip is not None
    full, cut = _stars(wcs, (4000, 4072), margin=180.0), _stars(wcs, (900, 700), margin=180.0)
    at = {m: (x, y) for m, x, y in zip(full["mag"], full["x"], full["y"])}
    assert cut["mag"].size > 10 and set(cut["mag"]) <= set(at)
    for m, x, y in zip(cut["mag"], cut["x"], cut["y"]):
        assert (x, y) == at[m]


# --- CCD scenes with a pointing draw the sky's stars ------------------------------------------

#: A CCD scene of stars alone, with explicit galactic coordinates so that the star counts do
#: not follow the pointing (by default they are the pointing's).
CCD_SCENE = {"seed": 11, "band": "r", "exptime": 30, "seeing": 0.7, "zenith": 30,
             "detector": {"type": "itl", "nx": 3000, "ny": 3000}, "sky": False,
             "noise": False, "cosmic_rays": 0, "satellites": [],
             "stars": {"galactic_l": 90.0, "galactic_b": 40.0, "mag_limit": 23.0}}


@pytest.fixture
def drawn(monkeypatch):
    """The stars a simulation draws (x, y, flux), recorded at inject.stars.draw_stars."""
    import inject.stars as stars_module

    calls = []
    real = stars_module.draw_stars

    def record(image, x, y, fluxes_e, *args, **kwargs):
        calls.append({"x": np.asarray(x), "y": np.asarray(y), "flux": np.asarray(fluxes_e)})
        return real(image, x, y, fluxes_e, *args, **kwargs)

    monkeypatch.setattr(stars_module, "draw_stars", record)
    return calls


def _simulate_file(tmp_path, drawn, name, **changes):
    """``inject simulate`` of CCD_SCENE with ``changes``: the stars it drew and the WCS its
    IMAGE header holds (read back by astropy)."""
    import yaml
    from astropy.io import fits
    from astropy.wcs import WCS

    from inject.cli.main import main

    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump({**CCD_SCENE, **changes}))
    out = tmp_path / f"{name}.fits"
    before = len(drawn)
    assert main(["simulate", str(path), "-o", str(out)]) == 0
    assert len(drawn) == before + 1
    with fits.open(out) as hdus:
        return drawn[-1], WCS(hdus["IMAGE"].header)


def _inside(stars, shape, border=50.0):
    ny, nx = shape
    return ((stars["x"] > border) & (stars["x"] < nx - 1 - border) & (stars["y"] > border)
            & (stars["y"] < ny - 1 - border))


def _same_sky(a, wa, b, wb, shape):
    """Every star of ``a`` (drawn through WCS ``wa``) that ``wb`` puts well inside the image
    is a star of ``b`` (the same flux) at that pixel to 0.01 px; returns how many, and the
    largest offset, px."""
    ra, dec = wa.pixel_to_world_values(a["x"], a["y"])
    xb, yb = wb.world_to_pixel_values(ra, dec)
    seen = _inside({"x": np.asarray(xb), "y": np.asarray(yb)}, shape)
    at = {f: (x, y) for f, x, y in zip(b["flux"], b["x"], b["y"])}  # fluxes are unique
    worst = 0.0
    for f, x, y in zip(a["flux"][seen], xb[seen], yb[seen]):
        assert f in at, "a star of the sky is missing"
        worst = max(worst, math.hypot(x - at[f][0], y - at[f][1]))
    assert worst < 0.01
    return int(np.count_nonzero(seen)), worst


@pytest.mark.parametrize("other", [{"ra": 210.0, "dec": -30.0, "rotation": 110.0},
                                   {"ra": 210.0, "dec": -29.9, "rotation": 20.0}],
                         ids=["rotated-90-deg", "moved-0.1-deg"])
def test_a_ccd_scene_with_a_pointing_has_the_skys_stars(tmp_path, drawn, other):
    """`inject simulate` of a CCD scene at rotation 20, and at 110 or with the pointing moved
    0.1 deg north: each star the second image holds is a star of the first at the same
    RA/Dec, through the WCS each file's header gives (to 0.01 px)."""
    a, wa = _simulate_file(tmp_path, drawn, "a", pointing={"ra": 210.0, "dec": -30.0,
                                                            "rotation": 20.0})
    b, wb = _simulate_file(tmp_path, drawn, "b", pointing=other)
    n, _ = _same_sky(a, wa, b, wb, (3000, 3000))
    m, _ = _same_sky(b, wb, a, wa, (3000, 3000))
    assert min(n, m) > 50


def test_a_ccd_scene_without_a_pointing_draws_per_pixel_area():
    """Without a WCS the random stars are drawn over the pixels (and a core stamp's margin)
    from the scene's "stars" stream, as before."""
    from inject import Seeing, parse_scene
    from inject.scene import rng
    from inject.stars import add_star_field, psf_stamps, star_field

    scene = parse_scene({**CCD_SCENE, "detector": {"type": "itl", "nx": 1000, "ny": 800}})
    got = add_star_field(np.zeros((800, 1000)), scene, rng(scene.seed, "stars", 0))
    margin = psf_stamps(Seeing(0.7).profile(), 0.2).core_half
    expected = star_field(scene.stars, (800, 1000), 0.2, "r", rng(scene.seed, "stars", 0),
                          margin_px=margin)
    assert got["mag"].size > 15
    for key in ("x", "y", "mag"):
        np.testing.assert_array_equal(got[key], expected[key])


def test_a_ccd_scenes_sky_stars_follow_the_counts():
    """The stars a CCD scene with a pointing draws on its pixels, over 40 seeds: the model's
    N(<23) - N(<12) per deg^2 (Bahcall & Soneira at l = 90, b = 40) times the image's solid
    angle, within 4 sigma of Poisson's error; the solid angle from the corners' sky positions
    (a spherical quadrilateral: its angular excess)."""
    from inject import parse_scene
    from inject.stars import add_star_field, cumulative_counts

    shape = (1500, 2000)
    raw = {**CCD_SCENE, "detector": {"type": "itl", "nx": shape[1], "ny": shape[0]},
           "pointing": {"ra": 33.0, "dec": 61.0, "rotation": 35.0}}
    wcs = pointing_wcs(parse_scene(raw).pointing, shape, 0.2)
    counts = []
    for seed in range(1, 41):
        scene = parse_scene({**raw, "seed": seed})
        stars = add_star_field(np.zeros(shape), scene, None, wcs=wcs)
        ny, nx = shape
        on = ((stars["x"] >= -0.5) & (stars["x"] < nx - 0.5) & (stars["y"] >= -0.5)
              & (stars["y"] < ny - 0.5))
        counts.append(np.count_nonzero(on))
    corners = np.array(wcs.pixel_to_world_values([-0.5, nx - 0.5, nx - 0.5, -0.5],
                                                 [-0.5, -0.5, ny - 0.5, ny - 0.5]))
    v = np.stack([np.cos(np.radians(corners[1])) * np.cos(np.radians(corners[0])),
                  np.cos(np.radians(corners[1])) * np.sin(np.radians(corners[0])),
                  np.sin(np.radians(corners[1]))], axis=1)
    # Two spherical triangles (Van Oosterom & Strackee): tan(E/2) = |a.(b x c)| /
    # (1 + a.b + b.c + c.a).
    area_sr = sum(2 * math.atan2(abs(np.dot(a, np.cross(b, c))),
                                 1 + a @ b + b @ c + c @ a)
                  for a, b, c in ((v[0], v[1], v[2]), (v[0], v[2], v[3])))
    density = cumulative_counts(23.0, 90.0, 40.0) - cumulative_counts(12.0, 90.0, 40.0)
    expected = density * area_sr * (180 / math.pi) ** 2
    assert abs(np.mean(counts) - expected) < 4 * math.sqrt(expected / len(counts))


def test_a_ccd_scenes_stars_are_the_focal_plane_ccds(drawn):
    """A CCD scene pointed where focal-plane CCD R41_S00 looks (its centre pixel's sky
    position, the same rotation) draws that CCD's stars: each star of the focal-plane CCD
    that the scene's WCS puts inside its image is a scene star at that pixel, to 0.01 px
    (the focal-plane WCS has the field's distortion, the scene's is a plain TAN)."""
    from inject import parse_focal_scene, parse_scene, simulate
    from inject.exposure.ccd import add_focal_stars

    ccd = fp.ccd("R41_S00")
    boresight = {"ra": 80.0, "dec": -40.0, "rotation": 20.0}
    raw = {k: v for k, v in CCD_SCENE.items() if k != "detector"}
    fscene = parse_focal_scene({**raw, "pointing": boresight, "detectors": ["R41_S00"]})
    wf = ccd_wcs(ccd, fscene.pointing)
    focal = add_focal_stars(np.zeros(ccd.shape), fscene, ccd)
    focal = {"x": focal["x"], "y": focal["y"], "flux": focal["flux_e"]}
    ny, nx = ccd.shape
    ra, dec = wf.pixel_to_world_values((nx - 1) / 2, (ny - 1) / 2)
    raw = {**CCD_SCENE, "detector": {"type": ccd.vendor},
           "pointing": {"ra": float(ra), "dec": float(dec), "rotation": 20.0}}
    scene = parse_scene(raw)
    wc = pointing_wcs(scene.pointing, ccd.shape, 0.2)
    simulate(scene, wcs=wc)
    n, _ = _same_sky(focal, wf, drawn[-1], wc, ccd.shape)
    m, _ = _same_sky(drawn[-1], wc, focal, wf, ccd.shape)
    assert min(n, m) > 200
