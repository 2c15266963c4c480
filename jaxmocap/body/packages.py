"""Humanoids that ship inside other packages, used as they come (issue 36 item 1): each is
loaded by :func:`jaxmocap.body.load_body` from its own file in the installed package (never
copied or edited), its roles inferred. ``docs/results/test_world.md`` tabulates the roles
found per body; ``tests/test_package_bodies.py`` checks them against MuJoCo's kinematics.

The test world draws on the two whose root link is the pelvis (the DeepMimic clips drive a
pelvis): pybullet's DeepMimic humanoid (a URDF in 4x units, Y up, loaded as pybullet loads it:
``scale=0.25, up="y"``) and dm_control's CMU humanoid (MJCF). dm_control's and gymnasium's
humanoids hang their arms from a torso root at chest height and their elbows never straighten;
they load (and the tests use them) but a clip placed by its pelvis leaves them 0.3 m low.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

from jaxmocap.errors import InputError

# pybullet_envs/deep_mimic/env/humanoid_stable_pd.py loads humanoid.urdf with globalScaling=0.25
# (the DeepMimic clips are in those units too: jaxmocap.synth.deepmimic uses the same constant)
DEEPMIMIC_SCALE = 0.25

# name -> (package, path inside it, load_body keywords)
PACKAGE_BODIES = {
    "deepmimic": ("pybullet_data", ("humanoid", "humanoid.urdf"),
                  {"scale": DEEPMIMIC_SCALE, "up": "y"}),
    "cmu": ("dm_control", ("suite", "humanoid_CMU.xml"), {}),
    "dmc_humanoid": ("dm_control", ("suite", "humanoid.xml"), {}),
    "gym_humanoid": ("gymnasium", ("envs", "mujoco", "assets", "humanoid.xml"), {}),
    "pybullet_mjcf": ("pybullet_data", ("mjcf", "humanoid.xml"), {}),
}


def package_body_file(name: str) -> tuple[Path, dict]:
    """(the body file inside its installed package, the ``load_body`` keywords it needs),
    located without importing the package."""
    if name not in PACKAGE_BODIES:
        raise InputError(f"package body {name!r}: expected one of {sorted(PACKAGE_BODIES)}")
    package, parts, kw = PACKAGE_BODIES[name]
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise InputError(f"package body {name!r}: the package {package!r} is not installed "
                         "(pip install jaxmocap[dev])")
    path = Path(next(iter(spec.submodule_search_locations))).joinpath(*parts)
    if not path.is_file():
        raise InputError(f"package body {name!r}: {path} is missing from {package}")
    return path, dict(kw)


def package_body(name: str):
    """The :class:`~jaxmocap.body.BodyModel` of a package body, roles inferred."""
    from jaxmocap.body.load import load_body

    path, kw = package_body_file(name)
    return load_body(path, **kw)


__all__ = ["PACKAGE_BODIES", "package_body", "package_body_file"]
