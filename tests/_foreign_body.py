"""A body the project has never seen, written as URDF and as MJCF (same body, ball joints).

Other proportions than the bundled body (-15 %..+15 % per segment), links named ``left_*`` /
``right_*`` / ``hips`` / ``torso``, limbs made of boxes and cylinders, the torso one box, a
separate neck link (head fixed on it), legs in trousers and shoes. Shared by test_body_roles.py and
the retargeting / tracker tests.
"""

from __future__ import annotations

from pathlib import Path

SHIRT = "0.80 0.10 0.10 1"  # torso
SLEEVE = "0.10 0.60 0.20 1"  # upper arms
CUFF = "0.10 0.20 0.80 1"  # forearms
TROUSERS = "0.15 0.15 0.25 1"
SHOES = "0.05 0.05 0.05 1"
SKIN = "0.90 0.72 0.60 1"

# Segment sizes (m); bundled values in comments.
SHOULDER_Y = 0.205  # 0.18
SHOULDER_Z = 0.46  # 0.40 above the chest joint
UPPER_ARM = 0.26  # 0.30
FOREARM = 0.29  # 0.26
NECK_Z = 0.50  # 0.43
SPINE_Z = 0.11  # 0.10
HAND = 0.17  # hand box length


def _lr(side: str) -> tuple[str, float]:
    return ("left", 1.0) if side == "l" else ("right", -1.0)


def foreign_urdf(path: Path) -> Path:
    """Write the foreign body as URDF (spherical joints) to ``path``; returns it."""
    mats = (f'<material name="shirt"><color rgba="{SHIRT}"/></material>'
            f'<material name="skin"><color rgba="{SKIN}"/></material>')

    def link(name, geoms=""):
        return f'<link name="{name}">{geoms}</link>'

    def vis(name, geom, xyz="0 0 0", rpy="0 0 0", rgba=SKIN):
        return (f'<visual name="{name}"><origin xyz="{xyz}" rpy="{rpy}"/><geometry>{geom}'
                f'</geometry><material name="m_{name}"><color rgba="{rgba}"/></material></visual>')

    def joint(name, jtype, parent, child, xyz, axis="1 0 0", lim=(-1.0, 1.0)):
        ax = f'<axis xyz="{axis}"/>' if jtype == "revolute" else ""
        li = (f'<limit lower="{lim[0]}" upper="{lim[1]}" effort="1" velocity="1"/>'
              if jtype == "revolute" else "")
        return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/>'
                f'<child link="{child}"/><origin xyz="{xyz}"/>{ax}{li}</joint>')

    parts = [mats,
             link("hips", vis("hips_box", '<box size="0.24 0.34 0.16"/>', "0 0 0.02",
                              rgba=TROUSERS)),
             joint("waist", "spherical", "hips", "torso", f"0 0 {SPINE_Z}"),
             link("torso", vis("torso_box", '<box size="0.22 0.36 0.52"/>', "0 0 0.24",
                               rgba=SHIRT)),
             joint("lower_neck", "spherical", "torso", "neck", f"0 0 {NECK_Z}"),
             link("neck", vis("neck_cyl", '<cylinder radius="0.05" length="0.08"/>',
                              "0 0 0.04")),
             joint("head_fix", "fixed", "neck", "head", "0 0 0.08"),
             link("head", vis("skull", '<sphere radius="0.105"/>', "0 0 0.09"))]
    for s in "lr":
        w, y = _lr(s)
        parts += [
            joint(f"{w}_shoulder", "spherical", "torso", f"{w}_upper_arm",
                  f"0 {y * SHOULDER_Y} {SHOULDER_Z}"),
            link(f"{w}_upper_arm", vis(f"{w}_upper_arm_box", '<box size="0.09 0.10 0.24"/>',
                                       f"0 0 {-UPPER_ARM / 2}", rgba=SLEEVE)),
            joint(f"{w}_elbow", "revolute", f"{w}_upper_arm", f"{w}_forearm",
                  f"0 0 {-UPPER_ARM}", "0 -1 0", (0.0, 2.6)),
            link(f"{w}_forearm", vis(f"{w}_forearm_cyl", '<cylinder radius="0.038" '
                                     f'length="{FOREARM - 0.04}"/>', f"0 0 {-FOREARM / 2}",
                                     rgba=CUFF)),
            joint(f"{w}_wrist", "revolute", f"{w}_forearm", f"{w}_hand", f"0 0 {-FOREARM}",
                  "1 0 0", (-1.2, 1.2)),
            link(f"{w}_hand", vis(f"{w}_hand_box", f'<box size="0.05 0.09 {HAND}"/>',
                                  f"0 0 {-HAND / 2}")),
            joint(f"{w}_hip", "spherical", "hips", f"{w}_thigh", f"0 {y * 0.095} -0.05"),
            link(f"{w}_thigh", vis(f"{w}_thigh_cyl", '<cylinder radius="0.07" length="0.40"/>',
                                   "0 0 -0.20", rgba=TROUSERS)),
            joint(f"{w}_knee", "revolute", f"{w}_thigh", f"{w}_shin", "0 0 -0.42", "0 1 0",
                  (0.0, 2.5)),
            link(f"{w}_shin", vis(f"{w}_shin_cyl", '<cylinder radius="0.05" length="0.38"/>',
                                  "0 0 -0.20", rgba=TROUSERS)),
            joint(f"{w}_ankle", "fixed", f"{w}_shin", f"{w}_foot", "0 0 -0.42"),
            link(f"{w}_foot", vis(f"{w}_shoe", '<box size="0.24 0.09 0.07"/>', "0.05 0 -0.03",
                                  rgba=SHOES)),
        ]
    path.write_text('<?xml version="1.0"?><robot name="foreign">' + "".join(parts) + "</robot>")
    return path


def foreign_mjcf(path: Path) -> Path:
    """Write the same body as MJCF (ball joints, free root) to ``path``; returns it."""

    def geom(name, gtype, size, pos, rgba):
        return f'<geom name="{name}" type="{gtype}" size="{size}" pos="{pos}" rgba="{rgba}"/>'

    def ball(name, pos="0 0 0"):
        return f'<joint name="{name}" type="ball" pos="{pos}" limited="false"/>'

    arms, legs = [], []
    for s in "lr":
        w, y = _lr(s)
        arms.append(
            f'<body name="{w}_upper_arm" pos="0 {y * SHOULDER_Y} {SHOULDER_Z}">'
            + ball(f"{w}_shoulder")
            + geom(f"{w}_upper_arm_box", "box", "0.045 0.05 0.12", f"0 0 {-UPPER_ARM / 2}", SLEEVE)
            + f'<body name="{w}_forearm" pos="0 0 {-UPPER_ARM}">'
            f'<joint name="{w}_elbow" type="hinge" axis="0 -1 0" range="0 2.6" limited="true"/>'
            + geom(f"{w}_forearm_cyl", "cylinder", f"0.038 {(FOREARM - 0.04) / 2}",
                   f"0 0 {-FOREARM / 2}", CUFF)
            + f'<body name="{w}_hand" pos="0 0 {-FOREARM}">'
            f'<joint name="{w}_wrist" type="hinge" axis="1 0 0" range="-1.2 1.2" limited="true"/>'
            + geom(f"{w}_hand_box", "box", f"0.025 0.045 {HAND / 2}", f"0 0 {-HAND / 2}", SKIN)
            + "</body></body></body>")
        legs.append(
            f'<body name="{w}_thigh" pos="0 {y * 0.095} -0.05">{ball(f"{w}_hip")}'
            + geom(f"{w}_thigh_cyl", "cylinder", "0.07 0.20", "0 0 -0.20", TROUSERS)
            + f'<body name="{w}_shin" pos="0 0 -0.42">'
            f'<joint name="{w}_knee" type="hinge" axis="0 1 0" range="0 2.5" limited="true"/>'
            + geom(f"{w}_shin_cyl", "cylinder", "0.05 0.19", "0 0 -0.20", TROUSERS)
            + f'<body name="{w}_foot" pos="0 0 -0.42">'
            + geom(f"{w}_shoe", "box", "0.12 0.045 0.035", "0.05 0 -0.03", SHOES)
            + "</body></body></body>")
    text = (
        '<mujoco model="foreign"><compiler angle="radian"/><worldbody>'
        '<body name="hips" pos="0 0 0"><freejoint name="root"/>'
        + geom("hips_box", "box", "0.12 0.17 0.08", "0 0 0.02", TROUSERS)
        + f'<body name="torso" pos="0 0 {SPINE_Z}">{ball("waist")}'
        + geom("torso_box", "box", "0.11 0.18 0.26", "0 0 0.24", SHIRT)
        + f'<body name="neck" pos="0 0 {NECK_Z}">{ball("lower_neck")}'
        + geom("neck_cyl", "cylinder", "0.05 0.04", "0 0 0.04", SKIN)
        + '<body name="head" pos="0 0 0.08">'
        + geom("skull", "sphere", "0.105", "0 0 0.09", SKIN)
        + "</body></body>" + "".join(arms) + "</body>" + "".join(legs)
        + "</body></worldbody></mujoco>"
    )
    path.write_text(text)
    return path
