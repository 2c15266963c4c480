"""``jaxmocap body``: the bundled upper body scaled to a subject's measurements -> URDF / MJCF.

Scaling, naming conventions and primitive swaps are :mod:`jaxmocap.body.scale`; the file
formats are :mod:`jaxmocap.body.write` (``.urdf`` -> URDF, ``.xml`` / ``.mjcf`` -> MJCF).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxmocap.errors import InputError

EPILOG = """examples:
  jaxmocap body --height 1.62 --shoulder-width 0.34 --upper-arm 0.28 --forearm 0.25 --out body.urdf
  jaxmocap body --height 1.85 --naming left_right --limbs box --out tall.xml

Measurements are metres: height (floor to top of head), shoulder width (between the shoulder
joint centres), upper arm (shoulder to elbow joint), forearm (elbow to wrist joint). A missing
one follows the height; the bundled body is 1.65 / 0.36 / 0.30 / 0.26 m.
"""


def add_parser(sub) -> None:
    p = sub.add_parser("body", help="write the bundled body scaled to measurements (URDF/MJCF)",
                       description=__doc__.splitlines()[0], epilog=EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--height", type=float, metavar="M", help="floor to top of head")
    p.add_argument("--shoulder-width", type=float, metavar="M",
                   help="between the shoulder joint centres")
    p.add_argument("--upper-arm", type=float, metavar="M", help="shoulder to elbow joint")
    p.add_argument("--forearm", type=float, metavar="M", help="elbow to wrist joint")
    p.add_argument("--naming", default="jaxmocap", metavar="STYLE",
                   help="link/joint names: jaxmocap (l_upper_arm), left_right (left_upper_arm) "
                   "or mixamo (LeftArm) (default: %(default)s)")
    p.add_argument("--limbs", choices=("capsule", "cylinder", "box"), default="capsule",
                   help="primitive of the limbs (default: %(default)s)")
    p.add_argument("--out", required=True, metavar="FILE",
                   help="output file: .urdf (URDF) or .xml/.mjcf (MJCF)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from jaxmocap.body.scale import NAMINGS, measure, rename_body, scale_body, swap_capsules
    from jaxmocap.body.write import write_mjcf, write_urdf
    from jaxmocap.io.atomic import check_output_file

    out = Path(args.out)
    suffix = out.suffix.lower()
    if suffix not in (".urdf", ".xml", ".mjcf"):
        raise InputError(f"--out {out}: expected a .urdf, .xml or .mjcf file name")
    if args.naming not in NAMINGS:
        raise InputError(f"--naming {args.naming!r}: expected one of {sorted(NAMINGS)}")
    check_output_file(out)
    sb = scale_body(height=args.height, shoulder_width=args.shoulder_width,
                    upper_arm=args.upper_arm, forearm=args.forearm)
    model = swap_capsules(sb.model, args.limbs)
    got = measure(model, sb.pelvis_height)
    if suffix == ".urdf":
        write_urdf(model, out, link_names=args.naming)
    else:
        write_mjcf(model, out, link_names=args.naming)
    named = rename_body(model, args.naming)
    print(f"jaxmocap body: wrote {out} ({named.chain.n_links} links, {named.n_dof} DOFs, "
          f"{named.geometry.n_geoms} geoms): height {got['height']:.3f} m, shoulder width "
          f"{got['shoulder_width']:.3f} m, upper arm {got['upper_arm']:.3f} m, forearm "
          f"{got['forearm']:.3f} m (pelvis standing at {sb.pelvis_height:.3f} m)")
    return 0
