"""Optional satellite brightness from lumos-sat's BRDF models (``pip install lumos-sat
--no-deps``), in place of the paper's scaling, for an orbit's streak.

A satellite of an ``orbit:`` scene may give ``lumos: {surfaces: [...], earthshine: false,
earth_albedo: 0.3}``: each surface ``{area: m^2, normal: [x, y, z], brdf: {type: lambertian,
albedo} | {type: phong, Kd, Ks, n} | {type: abg, A, B, g} | {type: binomial, B, C, d, l1}}``
(binomial: Greynolds's model, lumos's BINOMIAL, ``B`` and ``C`` matrices of as many rows,
``l1`` an integer), normals in lumos's brightness frame (z away from the Earth's centre, the
Sun in the y-z plane at +y). Each vertex of the
pass then gets lumos's AB magnitude at that instant (Sun and satellite alt/az from the site),
dimmed by the pass's penumbra. lumos places the satellite by its alt/az and height above a
sphere of 6378 km with the observer on it; the height given is the one that puts it at the
pass's true range there (``sqrt(R^2 + r^2 + 2 R r sin(alt)) - R``), so that its 1/r^2 is the
pass's (the geodetic height, which lumos's docs name, leaves the range ~0.5% off at Rubin's
latitude: 0.01 mag). The pass decides the shadow: lumos's own (a point Sun behind its
sphere) ends in the middle of the pass's penumbra, and a sample the pass has lit but lumos in
its shadow takes lumos's magnitude with the Sun at that shadow's edge (grazing the limb, as
through the penumbra), dimmed by the penumbra. That magnitude is turned into the
``mag`` the streak model scales with ``cos(theta_N) / r^2`` so that the model's apparent
magnitude is lumos's. lumos computes that magnitude at one wavelength (532 nm,
``lumos.constants.WAVELENGTH``), whatever the scene's band: it is taken as the band's.

lumos computes earthshine only with an Earth BRDF (with none it calls ``None``): with
``earthshine: true`` the Earth is Lambertian of albedo ``earth_albedo`` (0.3 by default).
"""
import numpy as np

from inject.errors import SceneError
from inject.schema import check_keys, number

#: Parameters of each BRDF type (lumos.brdf.library's LAMBERTIAN, PHONG, ABG, BINOMIAL).
BRDF_KEYS = {"lambertian": ("albedo",), "phong": ("Kd", "Ks", "n"), "abg": ("A", "B", "g"),
             "binomial": ("B", "C", "d", "l1")}
#: The faintest magnitude given to a vertex lumos sees dark (surfaces turned away).
DARK_MAG = 99.0


def _lumos():
    try:
        import lumos.brdf.library
        import lumos.calculator
        import lumos.constants
        import lumos.conversions
        import lumos.geometry
    except ImportError:
        # lumos-sat pins old numpy/astropy, so inject never installs it itself: say how.
        raise SceneError("lumos: BRDF brightness needs lumos-sat, which is installed apart: "
                         "make install-lumos (or pip install --no-deps lumos-sat==1.0.9)"
                         ) from None
    return lumos


def surfaces(where, spec):
    """lumos ``Surface`` objects and options from a ``lumos:`` mapping.

    Returns
    -------
    surfaces : list of lumos.geometry.Surface
    earth_brdf : callable or None
        None: no earthshine.
    """

    lumos = _lumos()
    check_keys(where, spec, {"surfaces", "earthshine", "earth_albedo"}, {"surfaces"})
    items = spec["surfaces"]
    if not isinstance(items, list) or not items:
        raise SceneError(f"{where}.surfaces: needs a list of surfaces")
    out = []
    for j, surface in enumerate(items):
        here = f"{where}.surfaces[{j}]"
        check_keys(here, surface, {"area", "normal", "brdf"}, {"area", "normal", "brdf"})
        area = number(f"{here}.area", surface["area"])
        if not area > 0:
            raise SceneError(f"{here}.area={area}: must be > 0 (m^2)")
        normal = surface["normal"]
        if not isinstance(normal, list) or len(normal) != 3:
            raise SceneError(f"{here}.normal={normal!r}: needs [x, y, z]")
        n = np.array([number(f"{here}.normal", v) for v in normal])
        if not np.linalg.norm(n) > 0:
            raise SceneError(f"{here}.normal={normal!r}: must not be zero")
        brdf = surface["brdf"]
        kind = brdf.get("type") if isinstance(brdf, dict) else None
        if kind not in BRDF_KEYS:
            raise SceneError(f"{here}.brdf={brdf!r}: needs type: one of {', '.join(BRDF_KEYS)}")
        check_keys(f"{here}.brdf", brdf, {"type", *BRDF_KEYS[kind]}, {"type", *BRDF_KEYS[kind]})
        params = _binomial(f"{here}.brdf", brdf) if kind == "binomial" else \
            [number(f"{here}.brdf.{k}", brdf[k]) for k in BRDF_KEYS[kind]]
        make = getattr(lumos.brdf.library, kind.upper())
        out.append(lumos.geometry.Surface(area, n / np.linalg.norm(n), make(*params)))
    earth_brdf = None
    if spec.get("earthshine", False) is True:
        albedo = number(f"{where}.earth_albedo", spec.get("earth_albedo", 0.3))
        if not 0 <= albedo <= 1:
            raise SceneError(f"{where}.earth_albedo={albedo}: must be in [0, 1]")
        earth_brdf = lumos.brdf.library.LAMBERTIAN(albedo)
    elif spec.get("earthshine", False) is not False:
        raise SceneError(f"{where}.earthshine={spec['earthshine']!r}: must be true or false")
    return out, earth_brdf


def _binomial(where, brdf):
    """BINOMIAL's ``B``, ``C`` (2-D arrays of as many rows: the powers of V they weigh), ``d``
    and ``l1``, checked."""
    out = []
    for key in ("B", "C"):
        rows = brdf[key]
        if not (isinstance(rows, list) and rows and all(
                isinstance(r, list) and r and len(r) == len(rows[0]) for r in rows)):
            raise SceneError(f"{where}.{key}={rows!r}: needs a matrix, a list of rows of "
                             f"numbers of one length")
        out.append(np.array([[number(f"{where}.{key}", v) for v in r] for r in rows]))
    if len(out[0]) != len(out[1]):
        raise SceneError(f"{where}: B has {len(out[0])} rows, C {len(out[1])}: needs as many")
    return [*out, number(f"{where}.d", brdf["d"]), number(f"{where}.l1", brdf["l1"], int)]


def magnitudes(where, spec, dense, idx):
    """lumos's AB magnitude of the satellite at samples ``idx`` of a pass (no penumbra)."""
    from astropy import units as u
    from astropy.coordinates import AltAz, get_sun

    lumos = _lumos()
    surfs, earth_brdf = surfaces(where, spec)
    times = dense.utc[idx]
    sun = get_sun(times).transform_to(AltAz(obstime=times, location=dense.site.location))
    out = []
    radius = float(lumos.constants.EARTH_RADIUS)
    for k, i in enumerate(idx):
        sun_alt, sun_az = float(sun.alt.deg[k]), float(sun.az.deg[k])
        if sun_alt > 0:
            raise SceneError(f"{where}: lumos: the Sun is up at the site ({sun_alt:.1f} deg)")
        # The height at which lumos's sphere puts the satellite at the pass's range.
        rho = float(dense.range_km[i]) * u.km.to(u.m)
        height = np.sqrt(radius ** 2 + rho ** 2 + 2.0 * radius * rho *
                         np.sin(np.radians(float(dense.alt_deg[i])))) - radius
        # lumos's get_intensity_observer_frame in its two steps, so that the pass decides
        # the shadow: lumos's is a point Sun behind its sphere, whose edge runs through the
        # middle of the pass's penumbra (a finite Sun, the WGS84 Earth). Where it has a lit
        # sample in its shadow, the Sun is taken at its shadow's edge (grazing, as in the
        # penumbra) and the penumbra's dimming is added by the caller.
        obs_x, obs_y, obs_z, past = lumos.calculator.get_brightness_coords(
            np.array([float(dense.alt_deg[i])]), np.array([float(dense.az_deg[i])]),
            np.array([height]), sun_alt, sun_az)
        edge = float(np.arccos(radius / (radius + height)))
        flux = lumos.calculator.get_intensity_satellite_frame(
            surfs, float(height), min(float(past[0]), edge),
            (float(obs_x[0]), float(obs_y[0]), float(obs_z[0])), include_sun=True,
            include_earthshine=earth_brdf is not None, earth_brdf=earth_brdf)
        flux = float(np.asarray(flux))
        out.append(float(lumos.conversions.intensity_to_ab_mag(flux, clip=False))
                   if flux > 0 else DARK_MAG)
    return np.array(out)
