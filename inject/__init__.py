"""inject: realistic, range-defocused satellite streaks for Rubin/LSSTCam images.

The public API, imported on first use (``import inject`` itself loads nothing heavy)::

    import inject
    scene = inject.parse_scene(inject.load_scene_file("sample_fields/default.yaml"))
    result = inject.simulate(scene)
    model = inject.StreakModel(height_km=550, zenith_deg=70, phi_deg=90,
                               shape=inject.Box(7.25, 2.65), mag=5.0)

Names and the module that defines them are listed in ``_API``; ``dir(inject)`` shows them,
and ``__init__.pyi`` repeats them for type checkers and editors.
``inject.__version__`` is read from the git checkout the package runs from (or the installed
metadata) on first access; :mod:`inject._version` says how.
"""
import importlib

#: Public name -> defining module.
_API = {
    # errors
    **dict.fromkeys(("InjectError", "InputError", "SceneError", "FileFormatError",
                     "OutputError", "ResourceError", "OrbitError", "InputWarning",
                     "OrbitWarning", "RunError"), "inject.errors"),
    "RANGES": "inject.validate",
    # physics
    "LSST": "inject.instrument", "Telescope": "inject.instrument",
    "Geometry": "inject.geometry",
    "Box": "inject.satellite", "Disk": "inject.satellite", "shape_from_dict": "inject.satellite",
    "apparent_magnitude": "inject.photometry", "electron_rate": "inject.photometry",
    "Seeing": "inject.profile", "stationary_profile": "inject.profile",
    "StreakModel": "inject.streak",
    # tracks and rendering
    "Segment": "inject.trajectory", "Polyline": "inject.trajectory", "Track": "inject.trajectory",
    "Budget": "inject.render", "render_segment": "inject.render",
    "render_polyline": "inject.render", "render_brute_force": "inject.reference",
    # CCD scenes
    "load_scene_file": "inject.schema", "apply_overrides": "inject.schema",
    "DEFAULT_SCENE": "inject.config", "Scene": "inject.config", "parse_scene": "inject.config",
    "simulate": "inject.scene", "render_streaks": "inject.scene", "SceneResult": "inject.scene",
    "add_streaks": "inject.addstreak",
    # wings
    "Pointing": "inject.camera.wcs", "ccd_wcs": "inject.camera.wcs",
    "pointing_wcs": "inject.camera.wcs",
    "Orbit": "inject.orbits.passes", "Exposure": "inject.orbits.passes",
    "Site": "inject.orbits.passes", "compute_pass": "inject.orbits.passes",
    "resolve_ccd_orbits": "inject.orbits.tracks",
    "parse_focal_scene": "inject.exposure.scene", "make_plan": "inject.exposure.plan",
    "simulate_ccd": "inject.exposure.ccd",
    "read_exposure": "inject.io.reader", "write_exposure": "inject.io.fits",
    "read_truth": "inject.io.fits",
    "write_exr": "inject.io.exr",
    "mask_image": "inject.masking", "MaskingError": "inject.masking",
}

__all__ = ["__version__", *_API]


def __getattr__(name):
    if name == "__version__":  # on first access: it may run git
        from inject._version import get_version
        globals()[name] = get_version()
        return globals()[name]
    module = _API.get(name)
    if module is None:
        raise AttributeError(f"module 'inject' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # once
    return value


def __dir__():
    return sorted(__all__)
