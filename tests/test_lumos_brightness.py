"""Optional lumos-sat BRDF brightness of an orbit's streak (skipped without lumos-sat)."""
from pathlib import Path

import numpy as np
import pytest

from inject import load_scene_file

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "sample_fields" / "pass_example.yaml"
PLATE = {"surfaces": [{"area": 10.0, "normal": [0, 0, -1],  # a nadir-facing plate
                       "brdf": {"type": "lambertian", "albedo": 0.5}}]}


def _raw(lumos):
    raw = {**load_scene_file(str(SCENE)), "exptime": 2.0, "time": "2026-06-15T23:29:59"}
    raw["satellites"] = [{**raw["satellites"][0], "lumos": lumos}]
    return raw


def test_vertices_take_lumos_magnitudes():
    """Each vertex's apparent magnitude (the streak model's, after its cos/r^2 scaling) is
    lumos's for that sample (its alt/az, the Sun's alt/az from the site, and the height at
    which lumos's 6378 km sphere puts the satellite at the pass's range, by the triangle
    Earth's centre - observer - satellite)."""
    calc = pytest.importorskip("lumos.calculator", reason="needs lumos-sat: make install-lumos")
    import lumos.brdf.library
    import lumos.constants
    import lumos.conversions
    import lumos.geometry
    from astropy.coordinates import AltAz, get_sun

    from inject import Exposure, Orbit, compute_pass, parse_focal_scene
    from inject.exposure.plan import vertex_model
    from inject.orbits.passes import TRACK_STEP_S
    fscene = parse_focal_scene(_raw(PLATE))
    track = fscene.tracks[0]
    pointing = fscene.pointing
    dense = compute_pass(Orbit.read_tle(str(ROOT / "sample_fields" / "example_starlink_like.tle")),
                         Exposure("2026-06-15T23:29:59", 2.0),
                         pointing, step_s=TRACK_STEP_S)
    x, y = dense.focal_mm()
    plate = [lumos.geometry.Surface(10.0, np.array([0.0, 0.0, -1.0]),
                                    lumos.brdf.library.LAMBERTIAN(0.5))]
    for xv, yv, values in list(zip(track.xs, track.ys, track.values))[::4]:
        i = int(np.nanargmin(np.hypot(x - xv, y - yv)))
        sun = get_sun(dense.utc[i]).transform_to(AltAz(obstime=dense.utc[i],
                                                       location=dense.site.location))
        radius, rho = lumos.constants.EARTH_RADIUS, dense.range_km[i] * 1e3
        height = np.sqrt(radius ** 2 + rho ** 2
                         + 2 * radius * rho * np.sin(np.radians(dense.alt_deg[i]))) - radius
        flux = calc.get_intensity_observer_frame(
            plate, height, dense.alt_deg[i], dense.az_deg[i],
            sun.alt.deg, sun.az.deg, include_earthshine=False)
        expected = lumos.conversions.intensity_to_ab_mag(float(flux), clip=False)
        assert vertex_model(fscene, 0, values).apparent_mag == pytest.approx(expected, abs=1e-6)
    # Earthshine (lumos needs an Earth BRDF for it: a Lambertian Earth) adds light.
    lit = parse_focal_scene(_raw({**PLATE, "earthshine": True})).tracks[0]
    assert all(a["mag"] < b["mag"] for a, b in zip(lit.values, track.values))


def test_lumos_inputs_are_checked():
    pytest.importorskip("lumos", reason="needs lumos-sat: make install-lumos")
    from inject import SceneError, parse_focal_scene
    bad = {"surfaces": [{"area": 1, "normal": [0, 0, 0], "brdf": {"type": "lambertian",
                                                                  "albedo": 0.5}}]}
    with pytest.raises(SceneError, match=r"surfaces\[0\]\.normal"):
        parse_focal_scene(_raw(bad))
    with pytest.raises(SceneError, match="type: one of"):
        parse_focal_scene(_raw({"surfaces": [{"area": 1, "normal": [0, 0, 1],
                                              "brdf": {"type": "mirror"}}]}))
    binomial = {"type": "binomial", "B": [[1.0, -30.0]], "C": [[1.0, 2.0], [3.0, 4.0]],
                "d": 3.0, "l1": -3}
    with pytest.raises(SceneError, match="B has 1 rows, C 2: needs as many"):
        parse_focal_scene(_raw({"surfaces": [{"area": 1, "normal": [0, 0, -1],
                                              "brdf": binomial}]}))
    with pytest.raises(SceneError, match=r"brdf\.C=.*needs a matrix"):
        parse_focal_scene(_raw({"surfaces": [{"area": 1, "normal": [0, 0, -1],
                                              "brdf": {**binomial, "C": [[1.0], [2.0, 3.0]]}}]}))
    with pytest.raises(SceneError, match=r"brdf\.l1=-2\.5: must be an integer"):
        parse_focal_scene(_raw({"surfaces": [{"area": 1, "normal": [0, 0, -1],
                                              "brdf": {**binomial, "C": [[1.0, 2.0]],
                                                       "l1": -2.5}}]}))
    raw = _raw(PLATE)
    raw["satellites"][0] = {k: v for k, v in raw["satellites"][0].items() if k != "orbit"} | {
        "height": 550, "track": {"x0_mm": 0, "y0_mm": 0, "angle": 0}}
    with pytest.raises(SceneError, match="lumos: only with an orbit"):
        parse_focal_scene(raw)


def test_without_lumos_a_clear_error(no_lumos):
    from inject import SceneError, parse_focal_scene

    with pytest.raises(SceneError, match="make install-lumos"):
        parse_focal_scene(_raw(PLATE))
