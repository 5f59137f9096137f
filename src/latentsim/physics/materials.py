"""The elastic materials a scene's ``material.model`` names, in one table.

A material is, per model kind it applies to (``rods``, ``shell``, ``tets``), one function
``terms(X, stencils, material) -> [EnergyTerm, ...]`` building the scene's elastic terms from

- ``X`` : (n, 3) float64 rest positions,
- ``stencils`` : the model's stencils, long tensors (``MODEL_STENCILS``: rods 'edges' (E, 2),
  'triples' (E, 3); shell 'triangles' (T, 3), 'hinges' (H, 4); tets 'tets' (E, 4)),
- ``material`` : the scene's material constants (``youngs_modulus``, ``poisson_ratio``, ...),

and a sentence saying what the energy is (table notes and captions, :func:`energy_description`).
:func:`register` enters one (material, model) pair; the scene (``scene.build_elastic``,
:func:`material_model`) and the config schema's list of names (``config.validate_config``)
read this table (``materials_of``, ``material_names``), so a new material is one function and
its registration line.  The table itself imports no torch (each ``terms`` imports its energy's module when
called): the workflow reads it when it validates a config and writes captions, before any job.  A term needs only its PyTorch ``local_energy`` (``physics.base``): every
solver runs a term without compiled kernels through autograd.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import importlib

__all__ = ["MATERIALS", "MODEL_STENCILS", "Material", "energy_description", "material_model", "material_names", "materials_of", "register",
           "tet_material"]

#: the stencil arrays each model kind hands its materials' ``terms``
MODEL_STENCILS = {"rods": ("edges", "triples"), "shell": ("triangles", "hinges"), "tets": ("tets",)}


@dataclass(frozen=True)
class Material:
    """One material of one model kind: its terms, its energy in words, the optional material keys
    it reads (beyond Young's modulus, Poisson's ratio, density, radius, thickness)."""

    terms: Callable
    description: str
    options: tuple = ()


#: material name -> {model kind -> Material}
MATERIALS: dict[str, dict[str, Material]] = {}


def register(name: str, model: str, terms: Callable, description: str, options: tuple = ()) -> None:
    """Enter material ``name`` for the model kind ``model`` (a key of ``MODEL_STENCILS``)."""
    if model not in MODEL_STENCILS:
        raise ValueError(f"model '{model}': use one of {', '.join(MODEL_STENCILS)}")
    MATERIALS.setdefault(name, {})[model] = Material(terms, description, tuple(options))


def material_names() -> tuple[str, ...]:
    """The registered material names, in registration order."""
    return tuple(MATERIALS)


def materials_of(model: str) -> tuple[str, ...]:
    """The names of the materials model kind ``model`` offers, in registration order."""
    return tuple(name for name, kinds in MATERIALS.items() if model in kinds)


def _constants(material: dict):
    return float(material["youngs_modulus"]), float(material["poisson_ratio"])


def tet_material(module: str, term: str) -> Callable:
    """``terms`` of a tet material whose term is the class ``term`` of ``latentsim.physics.<module>``, called as
    ``term(X, tets, youngs_modulus, poisson_ratio)``."""

    def terms(X, st, material):
        cls = getattr(importlib.import_module(f"latentsim.physics.{module}"), term)  # as the other terms: when built
        return [cls(X, st["tets"], *_constants(material))]

    return terms


def stvk_rods(X, st, material):
    """Stretch and bend of round rods, ks = Y pi r^2, kb = Y pi r^4 / 4 (``rods.rod_stiffness``)."""
    from latentsim.physics import rods  # torch: when the terms are built, not when the table is read

    ks, kb = rods.rod_stiffness(float(material["youngs_modulus"]), float(material["radius"]))
    return [rods.RodStretch(X, st["edges"], ks), rods.RodBend(X, st["triples"], kb)]


def stvk_shell(X, st, material):
    """The plane-stress StVK membrane and the hinge with kB = D/6: Grinspun's hinge weight
    3|e|^2/(A1+A2) with k_b = D converges to 6x the plate energy D/2 kappa^2 per area (measured in
    tests/physics/test_energy_shells.py); 1/6 calibrates it."""
    from latentsim.physics import shells  # torch: when the terms are built, not when the table is read

    Y, nu = _constants(material)
    h = float(material["thickness"])
    return [shells.ShellMembraneStVK(X, st["triangles"], Y, nu, h), shells.ShellHinge(X, st["hinges"], Y, nu, h, stiffness_scale=1.0 / 6.0)]


def stvk_nm_shell(X, st, material):
    """The Neural Modes authors' membrane and hinge (kB = D/2, or ``bending_stiffness``)."""
    from latentsim.physics import stvk_nm  # torch: when the terms are built, not when the table is read

    Y, nu = _constants(material)
    h, kb = float(material["thickness"]), material.get("bending_stiffness")
    return [stvk_nm.ShellMembraneNM(X, st["triangles"], Y, nu, h),
            stvk_nm.neural_modes_hinge(X, st["hinges"], Y, nu, h, None if kb is None else float(kb))]  # fmt: skip


register("stvk", "rods", stvk_rods, "the project's discrete rods (stretch and bend, physics.rods)")
register("stvk", "shell", stvk_shell, "the project's StVK shell (plane-stress membrane with lam/2 (tr E)^2, hinge kB = D/6; physics.shells)")
register("stvk", "tets", tet_material("tets", "StVKTets"), "the project's StVK tets (V (mu ||E||^2 + lam/2 (tr E)^2); physics.tets)")
register("stvk_nm", "shell", stvk_nm_shell,
         "stvk_nm, the Neural Modes authors' discrete shell (membrane h A (mu tr(E^2) + lam/2 (J - 1)^2) with the 3D Lame "
         "constants and J the area ratio, hinge 3 kB |e|^2 / (A1 + A2) (theta - theta0)^2; physics.stvk_nm)",
         options=("bending_stiffness",))  # fmt: skip
register("stvk_nm", "tets", tet_material("stvk_nm", "TetsNM"),
         "stvk_nm, the Neural Modes authors' StVK tets (V (mu ||E||^2 + lam (det F - 1)^2); physics.stvk_nm)")  # fmt: skip
register("neohookean", "tets", tet_material("neohookean", "StableNeoHookeanTets"),
         "stable neo-Hookean tets (Smith, de Goes and Kim 2018; physics.neohookean)")  # fmt: skip


def material_model(model: str, material: dict) -> str:
    """The scene's ``material.model`` (default 'stvk'), checked against those its ``model`` offers,
    and its optional keys (``Material.options``) against those the material reads.

    Raises
    ------
    ValueError naming the key and the value when the model has no such material, or the material
    does not read an optional key the scene sets.
    """
    if model not in MODEL_STENCILS:
        raise ValueError(f"model '{model}': use one of {', '.join(MODEL_STENCILS)}")
    law = str(material.get("model", "stvk"))
    offered = materials_of(model)
    if law not in offered:
        raise ValueError(f"material.model '{law}' is not available for model '{model}': use one of {', '.join(offered)}")
    for name, kinds in MATERIALS.items():
        for kind, entry in kinds.items():
            for key in entry.options:
                if material.get(key) is not None and key not in MATERIALS[law][model].options:
                    raise ValueError(f"material.{key} applies to model '{kind}' with material.model '{name}' only "
                                     f"(got model '{model}', material.model '{law}')")  # fmt: skip
    return law


def energy_description(model: str, material: dict) -> str:
    """The scene's elastic energy in words: its ``material.model``'s formulas and its constants.

    Raises
    ------
    ValueError (from :func:`material_model`) naming the key and the value when the model has no such material.
    """
    law = material_model(model, material)
    consts = [f"E {float(material['youngs_modulus']):.3g} Pa", f"nu {float(material.get('poisson_ratio', 0.3)):g}"]
    if model == "shell":
        consts.append(f"h {float(material['thickness']):g} m")
        if material.get("bending_stiffness") is not None:
            consts.append(f"kB {float(material['bending_stiffness']):.3g} N m")
        elif law == "stvk_nm":
            consts.append("kB = D/2 = E h^3 / (24 (1 - nu^2))")
    elif model == "rods":
        consts.append(f"radius {float(material['radius']):g} m")
    return f"{MATERIALS[law][model].description}, {', '.join(consts)}"
