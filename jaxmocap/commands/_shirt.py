"""``track --method shirt``'s set-up pieces beside ``track.py``: the pose database of ``--db``
(or the cached one) and the tracker on the learned observation (issue 49: the default without
``--colors``)."""

from __future__ import annotations

import sys

from jaxmocap.errors import InputError


def shirt_database(args, body, garment):
    """The pose database of ``--db`` (refused in one line when it is not one for this body and
    shirt), else the cached one for them (built the first time)."""
    from jaxmocap.posedb import DatabaseError, load_database, load_or_build

    if args.db:
        try:
            return load_database(args.db, model=body, garment=garment)
        except FileNotFoundError:
            raise InputError(f"{args.db}: no such pose database (build one with `jaxmocap "
                             "build-db --out FILE.npz`)") from None
        except DatabaseError as e:
            raise InputError(str(e)) from None
    return load_or_build(model=body, garment=garment, progress=not args.quiet)


def shirt_inputs(args, body, garment, tuned):
    """``(IK covariances or None, pose database, Search)`` of ``--tuned`` / ``--ik-cov``,
    ``--db`` and ``--work-size``, shared by both of the shirt tracker's paths."""
    from jaxmocap.trackers.shirt import Search

    cov = None if tuned is None else tuned.ik_covariances(body)
    if args.ik_cov:
        from jaxmocap.ik import IKCovariances

        try:
            cov = IKCovariances.load(args.ik_cov)
        except ValueError as e:
            raise InputError(str(e)) from None
    db = shirt_database(args, body, garment)
    search = Search() if args.work_size is None else Search(work_size=args.work_size)
    return cov, db, search


def learned_shirt_tracker(args, body, cams, names, tuned):
    """The shirt tracker on the learned observation (issue 49; the default, ``--colors`` is the
    paper's set-up): steps 1 and 3 read the model of ``--observer``, or without it ``jaxmocap
    learn``'s for this body and shirt (the bundled one, or fine-tuned from it and cached: a
    progress bar the first time). No colour model or white balance is needed (the garment's
    albedo stands as the colour model the paper's structures carry, never read on this
    path)."""
    import jax.numpy as jnp

    from jaxmocap.color import ColorModel
    from jaxmocap.commands._body import garment_from_args
    from jaxmocap.observe import load as load_observer
    from jaxmocap.trackers.driver import ShirtFrameTracker, shirt_params
    from jaxmocap.trackers.shirt import Colours

    for flag, given in (("--colors", args.colors), ("--white-balance", args.white_balance)):
        if given:
            raise InputError(f"the learned observation classifies the pixels; {flag} goes with "
                             "--colors (Wang's colour model and white balance, the paper's "
                             "set-up)" if not args.observer else
                             f"--observer classifies the pixels; leave out {flag} (Wang's "
                             "colour model and white balance are the paper's path)")
    garment = garment_from_args(args, body)
    if tuned is not None:
        tuned.check_for("shirt", body, garment)
    if args.observer:
        observer, _ = load_observer(args.observer, body, garment)
    else:
        from jaxmocap.observe import learn

        observer, _, path = learn(body, garment, progress=not args.quiet)
        if not args.quiet:
            print(f"jaxmocap track: pixels classified by the learned observation {path} "
                  "(--colors COLORS_JSON for the paper's set-up)", file=sys.stderr)
    color = ColorModel(jnp.asarray(garment.colours) * 255,
                       jnp.tile(jnp.eye(3) * 100.0, (garment.n_colours, 1, 1)),
                       names=garment.colour_names)
    cov, db, search = shirt_inputs(args, body, garment, tuned)
    params = shirt_params(color, body, garment, cams, db, cov, args.validity or "learned",
                          search=search, colours=Colours(observer=observer))
    return ShirtFrameTracker(params, None, cams, names, color, None)
