"""Satellite shapes and their projected, range-scaled GalSim profiles.

A shape is defined in the satellite's body frame, in metres: ``x`` along the direction of motion,
``y`` across it, lying in the satellite's local horizontal plane (a nadir-pointing satellite). Seen
from the telescope at nadir angle ``theta_N`` the body is foreshortened by ``cos(theta_N)`` along
the satellite frame's y axis (the direction towards the telescope, paper section 2.4), then scaled
by ``1 / range`` into arcsec. The profiles returned here are in the *track frame*: arcsec, the
apparent direction of motion along +x, unit flux.
"""
from dataclasses import dataclass, field

import galsim
import numpy as np

from inject.errors import InputError
from inject.instrument import ARCSEC_PER_RAD
from inject.validate import finite, positive


def _track_frame_jacobian(range_km, nadir_angle_deg, phi_deg):
    """Linear map from body-frame metres to track-frame arcsec.

    Body frame -> satellite frame (rotate by phi: the motion is at phi from the satellite's x
    axis) -> sky plane (compress the satellite's y axis by cos theta_N) -> track frame (rotate
    the projected motion onto +x) -> arcsec.
    """
    phi = np.radians(phi_deg)
    cos_n = np.cos(np.radians(nadir_angle_deg))
    rot_phi = np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
    project = np.diag([1.0, cos_n])
    psi = np.arctan2(np.sin(phi) * cos_n, np.cos(phi))
    unrot = np.array([[np.cos(psi), np.sin(psi)], [-np.sin(psi), np.cos(psi)]])
    scale = ARCSEC_PER_RAD / (range_km * 1e3)
    return scale * unrot @ project @ rot_phi


class Shape:
    """Base class of satellite shapes; subclasses define :meth:`body_profile` and ``area_m2``."""

    def body_profile(self):
        """The shape in body-frame metres as a GalSim profile with flux equal to its area."""
        raise NotImplementedError

    @property
    def size_m(self):
        """Largest dimension, m (used for cheap width estimates and supports)."""
        raise NotImplementedError

    def profile(self, range_km, nadir_angle_deg=0.0, phi_deg=90.0, gsparams=None):
        """Projected shape in the track frame (arcsec, motion along +x), unit flux."""
        r = positive("range_km", range_km, scalar=True)
        jac = _track_frame_jacobian(r, finite("nadir_angle_deg", nadir_angle_deg, scalar=True),
                                    finite("phi_deg", phi_deg, scalar=True))
        prof = self.body_profile()
        if gsparams is not None:
            prof = prof.withGSParams(gsparams)
        return prof.transform(*jac.ravel()).withFlux(1.0)


@dataclass(frozen=True)
class Box(Shape):
    """A flat rectangle: ``length`` along the motion, ``width`` across, metres."""

    length: float
    width: float

    def __post_init__(self):
        object.__setattr__(self, "length", positive("length", self.length, scalar=True))
        object.__setattr__(self, "width", positive("width", self.width, scalar=True))

    @property
    def area_m2(self):
        return self.length * self.width

    @property
    def size_m(self):
        return float(np.hypot(self.length, self.width))

    def body_profile(self):
        return galsim.Box(self.length, self.width, flux=self.area_m2)


@dataclass(frozen=True)
class Disk(Shape):
    """A flat disk of ``radius`` metres."""

    radius: float

    def __post_init__(self):
        object.__setattr__(self, "radius", positive("radius", self.radius, scalar=True))

    @property
    def area_m2(self):
        return np.pi * self.radius ** 2

    @property
    def size_m(self):
        return 2.0 * self.radius

    def body_profile(self):
        return galsim.TopHat(self.radius, flux=self.area_m2)


@dataclass(frozen=True)
class Part:
    """One part of a :class:`Composite`: a shape, its centre offset in the body frame (m) and a
    relative reflectance (flux per unit area relative to the other parts)."""

    shape: Shape
    dx: float = 0.0
    dy: float = 0.0
    reflectance: float = 1.0

    def __post_init__(self):
        if not isinstance(self.shape, Shape):
            raise InputError("shape", self.shape, "must be a Box, Disk or Composite")
        object.__setattr__(self, "dx", finite("dx", self.dx, scalar=True))
        object.__setattr__(self, "dy", finite("dy", self.dy, scalar=True))
        object.__setattr__(self, "reflectance",
                           positive("reflectance", self.reflectance, scalar=True))


@dataclass(frozen=True)
class Composite(Shape):
    """A satellite made of several flat parts (bus, solar panels, dish), as in leosim.

    The parts' fluxes are proportional to area times reflectance.
    """

    parts: tuple = field(default_factory=tuple)

    def __post_init__(self):
        try:
            parts = tuple(self.parts)
        except TypeError:  # a number or a single Part
            parts = (self.parts,)
        if not parts:
            raise InputError("parts", self.parts, "a composite needs at least one part")
        if not all(isinstance(p, Part) for p in parts):
            raise InputError("parts", self.parts, "must be a sequence of Part")
        object.__setattr__(self, "parts", parts)

    @property
    def area_m2(self):
        return sum(p.shape.area_m2 for p in self.parts)

    @property
    def size_m(self):
        return max(np.hypot(p.dx, p.dy) * 2 + p.shape.size_m for p in self.parts)

    def body_profile(self):
        return galsim.Add([
            p.shape.body_profile().withFlux(p.shape.area_m2 * p.reflectance).shift(p.dx, p.dy)
            for p in self.parts])


def shape_from_dict(spec):
    """Build a shape from a scene mapping such as ``{type: box, length: 7.25, width: 2.65}``.

    A composite is ``{type: composite, parts: [{type: box, ..., dx: 0, dy: 3}, ...]}``.
    """
    if not isinstance(spec, dict) or "type" not in spec:
        raise InputError("shape", spec, "must be a mapping with a 'type' (box, disk, composite)")
    kind = spec["type"]
    keys = {"box": ("length", "width"), "disk": ("radius",), "composite": ("parts",)}
    if not isinstance(kind, str) or kind not in keys:  # a list or mapping is unhashable
        raise InputError("shape.type", kind, "unknown shape; choose box, disk or composite")
    extra = set(spec) - {"type", *keys[kind]}
    missing = set(keys[kind]) - set(spec)
    if extra or missing:
        problem = f"unknown keys {sorted(extra)}" if extra else f"missing keys {sorted(missing)}"
        raise InputError("shape", spec, f"{problem} for a {kind}")
    if kind == "composite":
        if not isinstance(spec["parts"], list) or not all(isinstance(p, dict)
                                                          for p in spec["parts"]):
            raise InputError("shape.parts", spec["parts"], "must be a list of shape mappings")
        parts = []
        for part in spec["parts"]:
            part = dict(part)
            placement = {k: part.pop(k) for k in ("dx", "dy", "reflectance") if k in part}
            parts.append(Part(shape_from_dict(part), **placement))
        return Composite(tuple(parts))
    return {"box": Box, "disk": Disk}[kind](*(spec[k] for k in keys[kind]))
