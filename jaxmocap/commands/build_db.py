"""``jaxmocap build-db``: build (or find in the cache) the pose database of Wang et al. §5.2
for a body and shirt (:mod:`jaxmocap.posedb`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxmocap.commands._body import add_body_args, body_from_args, garment_from_args
from jaxmocap.errors import UsageError
from jaxmocap.io.atomic import check_output_file
from jaxmocap.io.preflight import check_outputs
from jaxmocap.posedb import (
    DEFAULT_SIZE,
    SamplingConfig,
    SamplingError,
    build_database,
    cache_path,
    database_key,
    load_or_build,
)


def add_parser(sub) -> None:
    p = sub.add_parser("build-db", help="build (or find in the cache) the pose database "
                       "of Wang et al. §5.2")
    p.add_argument("--size", type=int, default=DEFAULT_SIZE,
                   help="number of poses (default: %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="sampling seed (default: %(default)s)")
    p.add_argument("--out", default=None,
                   help="write the database .npz here (default: the user's cache folder)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_body_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        config = SamplingConfig(size=args.size, seed=args.seed).validate()
    except SamplingError as err:
        raise UsageError(f"--size/--seed: {err}") from None
    model = body_from_args(args)
    garment = garment_from_args(args, model)
    if args.out is not None:
        out = Path(args.out)
        if out.suffix != ".npz":
            raise UsageError(f"--out {args.out}: expected a path ending in .npz")
        check_output_file(out)
        check_outputs([out], [args.body, args.garment])
        db = build_database(config, model, garment, out=out, progress=not args.quiet)
        where = out
    else:
        check_output_file(cache_path(database_key(config, model, garment)))
        db = load_or_build(config, model, garment, progress=not args.quiet)
        where = cache_path(db.key)
    print(f"pose database: {db.size} poses, key {db.key}, {where}")
    return 0
