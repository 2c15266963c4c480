"""``jaxmocap track``: videos, frame folders or live cameras -> poses (BVH, TRC, C3D, CSV, NPZ),
per-frame diagnostics and an optional overlay video (H.264 MP4 at the capture's frame rate).

The command drives either tracker through the frame protocol of :mod:`jaxmocap.trackers.driver`
(:class:`~jaxmocap.trackers.driver.ShirtFrameTracker`,
:class:`~jaxmocap.trackers.driver.StereoPFFrameTracker`,
:func:`~jaxmocap.trackers.driver.drive`). Every stepped frame's estimate is written, valid or
not, with its ``valid`` flag and the tracker's per-frame diagnostics beside it
(:mod:`jaxmocap.io.export` says how each format marks an invalid frame). Frames that cannot be
read are not stepped: their row is NaN (``valid`` 0) in every output and the command reports
them in one line (exit code 1). All outputs are written to temporaries (outside ``--out``,
:func:`jaxmocap.io.atomic.staging_dir`) and renamed into place only at the end, together, with
``run.json`` saying whether the run was complete. Everything that can be refused is refused
before the first frame is read: outputs that would touch an input, an ``--out`` holding an
earlier run's results (unless ``--overwrite``: the earlier set is then replaced as a whole),
cameras the tracker cannot use.

**Interrupts.** Ctrl-C (or SIGTERM) while frames are being tracked ends the loop; the frames
tracked so far are written as a complete result marked partial (``run.json`` ``complete``
false, ``poses.npz`` ``complete`` False, the printed line) and the exit code is 130. An
interrupt before the first frame was tracked (set-up, compilation) writes nothing (exit 130).

**Nothing tracked is lost** (:mod:`jaxmocap.io.journal`): every frame goes to a journal beside
``--out`` as it is tracked, with the tracker's state every ``--checkpoint`` seconds; the
outputs are made from it at the end and the journal is removed once they are in place. After
an interrupt, a ``kill -9``, a full disk or an output folder that became read-only the journal
stays, the message says where, and ``track --resume OUT`` continues from the checkpoint with
the interrupted run's settings (its outputs equal an uninterrupted run's).
"""

from __future__ import annotations

import argparse
import csv
import io
import itertools
import json
import os
import signal
import sys
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from jaxmocap.camera import Camera
from jaxmocap.commands._resume import (
    input_paths,
    keep_or_drop,
    non_negative_seconds,
    open_journal,
    refuse_over_journal,
    resumed_args,
)
from jaxmocap.errors import InputError
from jaxmocap.io.atomic import AtomicFiles, check_output_folder, output_folder_lock
from jaxmocap.io.cameras import load_cameras
from jaxmocap.io.export import FORMATS, pose_track, write_exports
from jaxmocap.io.journal import CHECKPOINT_EVERY_S, Journal, tracked_arrays
from jaxmocap.io.preflight import (
    check_outputs,
    check_stale,
    int_range,
    positive_float,
    unit_fraction,
)
from jaxmocap.io.sync import SYNC_MODES, SyncReader
from jaxmocap.io.video import VideoWriter, quiet_ffmpeg
from jaxmocap.kalman import DEFAULT_CUTOFF_HZ, smooth_poses
from jaxmocap.trackers.driver import (
    MAX_PARTICLES,
    VALIDITY,
    FrameResult,
    FrameTracker,
    ShirtFrameTracker,
    StereoPFFrameTracker,
    Tracked,
    diagnostics_table,
    drive,
    shirt_params,
)

__all__ = [
    "FrameResult",
    "FrameTracker",
    "ShirtFrameTracker",
    "StereoPFFrameTracker",
    "add_parser",
    "run",
    "track_frames",
]

DEFAULT_FPS = 30.0  # frame folders and live cameras that do not say
# The particle filter's compile time grows with the particle count (XLA folds constants of
# that size): 10,000,000 compiles for minutes; 100x the paper's 1000 is the bound.
MIN_BASELINE_M = 1e-3  # stereo: camera centres closer than this triangulate nothing
EXIT_INTERRUPTED = 130

EPILOG = """examples:
  # the colour shirt, two recorded cameras
  jaxmocap track --method shirt --cameras cameras.json --colors colors.json \\
      --white-balance white_balance.json cam0.mp4 cam1.mp4 --out results --overlay
  # the stereo particle filter on folders of frames, 500 particles
  jaxmocap track --method pf --cameras cameras.json left/ right/ --particles 500 --out results
  # live from camera 0 (one camera), 300 frames, pose drawn in a window
  jaxmocap track --method shirt --cameras cameras.json --colors colors.json 0 \\
      --max-frames 300 --show

outputs in --out: poses.bvh poses.trc poses.c3d poses.csv poses.npz (see --formats),
diagnostics.csv, run.json, overlay.mp4 (--overlay: H.264 at the capture's frame rate).
Every frame's estimate is written, valid or not: poses.npz/.csv hold it with its valid flag
and diagnostics; TRC and C3D mark invalid frames as missing markers; BVH holds every
estimate (its validity: diagnostics.csv). An
--out holding an earlier run's results is refused unless --overwrite (the earlier set is then
replaced as a whole). Exit codes: 0 done, 1 done but some frames were unreadable (reported),
2 bad input (nothing written), 130 interrupted (Ctrl-C or SIGTERM: the frames tracked so far,
marked partial in run.json and poses.npz; nothing if interrupted before the first frame).
Every frame is journalled beside --out as it is tracked: after an interrupt, kill -9, a full
disk or a read-only folder, `jaxmocap track --resume OUT` continues from the last checkpoint.
"""


def result_names() -> set[str]:
    """The files a run may leave in ``--out`` (its result set; with ``eval.json``, which
    `jaxmocap eval` writes there from those poses)."""
    return {f"poses.{f}" for f in FORMATS} | {"diagnostics.csv", "run.json", "overlay.mp4",
                                              "eval.json"}


# ----------------------------------------------------------------------------- the loop


def _has_display() -> bool:
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY")
                                                 or os.environ.get("WAYLAND_DISPLAY")):
        return False
    try:  # opencv-python-headless has no GUI: imshow raises
        cv2.namedWindow("jaxmocap")
        cv2.destroyWindow("jaxmocap")
    except cv2.error:
        return False
    return True


def _diagnostics_csv(names: Sequence[str], rows: list[tuple[int, bool, bool, dict]],
                     table: np.ndarray) -> str:
    """``diagnostics.csv``: frame, read, valid and the columns of ``table``
    (:func:`diagnostics_table` of ``rows``), empty where a value is missing or not finite."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "read", "valid", *names])
    for (t, read, valid, _), values in zip(rows, table, strict=True):
        w.writerow([t, int(read), int(valid),
                    *("" if not np.isfinite(v) else f"{v:.6g}" for v in values)])
    return buf.getvalue()


def _interrupt(err: BaseException) -> str | None:
    """The command line's reading of an exception in the frame loop (:mod:`jaxmocap.cli`):
    the interrupt it is (however a library wrapped it), acknowledged, or None."""
    from jaxmocap.cli import Terminated, acknowledge_interrupt, interrupt_received

    signum = interrupt_received()
    if not (isinstance(err, KeyboardInterrupt) or signum):
        return None
    acknowledge_interrupt()
    return "SIGTERM" if isinstance(err, Terminated) or signum == signal.SIGTERM else "SIGINT"


def track_frames(tracker: FrameTracker, reader: SyncReader, files: AtomicFiles, out: Path,
                 fps: float, overlay: bool = False, show: bool = False,
                 progress: bool = True, journal: Journal | None = None,
                 restore=None) -> Tracked:
    """:func:`jaxmocap.trackers.driver.drive` over ``reader``, with the overlay video (if
    asked, into ``files``) and the live window (``show``); an interrupt is read as the command
    line reads it. ``journal``: every instant is appended to it as it is tracked, with the
    tracker's checkpoint when due; the instants it already holds (a resumed run) are read and
    skipped, and the tracker continues from ``restore``."""
    state = {"writer": None, "size": None}
    n_dof = tracker.body.n_dof
    done = 0 if journal is None else journal.count
    has_checkpoint = callable(getattr(tracker, "checkpoint", None))

    def record(t, res):
        if journal is None:
            return
        if res is None:
            journal.append(t, False, False, np.full(n_dof, np.nan), {})
        else:
            journal.append(t, True, res.valid, res.q, res.diagnostics)
        if has_checkpoint and journal.checkpoint_due():
            journal.checkpoint(tracker.checkpoint())

    def on_frame(t, frames, res):
        record(t, res)
        view = None
        if frames is not None and (overlay or show):
            view = np.concatenate(list(tracker.draw(frames, res)), axis=1)
        if overlay:
            size = state["size"]
            if view is None:  # an unreadable instant: a dark frame keeps the timing
                view = None if size is None else np.full((size[1], size[0], 3), 30, np.uint8)
            if view is not None:
                if state["writer"] is None:
                    state["size"] = (view.shape[1], view.shape[0])
                    state["writer"] = VideoWriter(files.path(out / "overlay.mp4"), fps,
                                                  *state["size"])
                state["writer"].write(view)
        if show and view is not None:
            cv2.imshow("jaxmocap track", view[..., ::-1])
            if cv2.waitKey(1) & 0xFF in (ord("q"), 27):
                return True
        return None

    frames = itertools.islice(iter(reader), done, None)  # a resumed run's: read, not stepped
    prefix = None if journal is None else tracked_arrays(journal.resumed, n_dof)
    if journal is not None:
        journal.resumed = []  # handed over
    try:
        tracked = drive(tracker, frames, n_frames=reader.n_frames, on_frame=on_frame,
                        progress=progress, interrupt=_interrupt, prefix=prefix,
                        restore=restore)
    finally:
        if state["writer"] is not None:
            state["writer"].close()
    if journal is not None and tracked.interrupted is None and has_checkpoint and \
            journal.checkpointed < journal.count and journal.count > done:
        journal.checkpoint(tracker.checkpoint())  # all tracked: a resume only writes
    return tracked


def _learned_path(args) -> bool:
    """The shirt tracker on the learned observation: its default (issue 49); ``--colors`` is
    the paper's set-up."""
    return args.method == "shirt" and bool(args.observer or not args.colors)


def _make_tracker(args, cams: list[Camera], names: list[str]) -> FrameTracker:
    from jaxmocap.commands._body import body_from_args, garment_from_args
    from jaxmocap.commands._shirt import learned_shirt_tracker, shirt_inputs

    body = body_from_args(args)
    tuned = None
    if args.tuned:  # before the database, the colour model or the compile: exit 2 up front
        from jaxmocap.tuned import load_tuned

        if args.ik_cov:
            raise InputError("give --tuned (a tuned-parameters file) or --ik-cov, not both")
        tuned = load_tuned(args.tuned, args.method, body)  # the shirt's garment: below
    if args.method == "pf" and args.garment:
        raise InputError("--garment describes the colour shirt of --method shirt; the particle "
                         "filter (--method pf) segments a single-colour shirt and skin")
    if args.method == "pf":
        if args.pf_colors and args.skin != "default":
            raise InputError(f"--pf-colors gives the skin and shirt colours; leave out --skin "
                             f"{args.skin}")
        if args.pf_skin_grow and not args.pf_colors:
            raise InputError("--pf-skin-grow grows the skin map of the capture's colours; it "
                             "needs --pf-colors")
        return StereoPFFrameTracker(cams, args.particles, args.seed, args.skin, body,
                                    args.pf_colors, args.pf_skin_grow, args.pf_swivel,
                                    cue_widths=None if tuned is None else tuned.cue_widths())
    from jaxmocap.color import load_color_model

    if _learned_path(args):
        return learned_shirt_tracker(args, body, cams, names, tuned)
    color = load_color_model(args.colors)
    garment = garment_from_args(args, body, color if args.garment else None)
    if tuned is not None:
        tuned.check_for("shirt", body, garment)
    if color.n_colors != garment.n_colours:  # before the database, which may be built first
        raise InputError(f"{args.colors}: the colour model has {color.n_colors} colours, the "
                         f"shirt has {garment.n_colours}; fit one colour per shirt colour")
    W0 = room = None
    if args.white_balance:
        from jaxmocap.io.white_balance import load_room_colors, load_white_balance

        W0 = load_white_balance(args.white_balance, names)
        room = load_room_colors(args.white_balance)
    if not args.quiet:
        if color.shading is not None:
            print(f"jaxmocap track: {args.colors} was fitted for the shading-invariant colour "
                  f"distance: brightness {color.shading[0]:g}..{color.shading[1]:g}",
                  file=sys.stderr)
        if room is not None:
            print(f"jaxmocap track: {room.n_colors} room colours of {args.white_balance} are "
                  "background", file=sys.stderr)
    cov, db, search = shirt_inputs(args, body, garment, tuned)
    from jaxmocap.trackers.shirt import Colours

    params = shirt_params(color, body, garment, cams, db, cov, args.validity or "paper",
                          search=search, colours=Colours(shading=color.shading, scene_colors=room))
    return ShirtFrameTracker(params, W0, cams, names, color, room)


def add_parser(sub) -> None:
    p = sub.add_parser(
        "track", help="track poses in videos, frame folders or live cameras",
        description="Track the upper body with the colour-shirt tracker (Wang et al. 2011, "
        "--method shirt) or the stereo particle filter (Azad et al. 2007, --method pf). Give "
        "one input per camera of cameras.json, in its order: a video file, a folder of "
        "frames, or a camera index for live capture. Writes the poses (BVH, TRC, C3D, CSV, NPZ), "
        "per-frame diagnostics and optionally an overlay video into --out.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="*", metavar="INPUT",
                   help="per camera: video file, folder of frames, or camera index (0, 1, ...)")
    p.add_argument("--method", choices=("shirt", "pf"), default="shirt",
                   help="tracker: shirt (Wang et al.) or pf (Azad et al.) (default: %(default)s)")
    p.add_argument("--cameras", metavar="CAMERAS_JSON",
                   help="calibrated cameras (from `jaxmocap calibrate`), required")
    p.add_argument("--out", default="track_out", metavar="FOLDER",
                   help="output folder (default: %(default)s)")
    p.add_argument("--formats", default=",".join(FORMATS),
                   help="pose formats to write, comma separated (default: %(default)s)")
    p.add_argument("--overlay", action="store_true",
                   help="also write overlay.mp4 (skeleton, classified colours for shirt)")
    p.add_argument("--show", action="store_true",
                   help="show the current pose in a window (needs a display)")
    p.add_argument("--max-frames", type=int_range(1), metavar="N",
                   help="stop after N frames (needed to end a live capture without Ctrl-C)")
    p.add_argument("--fps", type=positive_float,
                   help=f"frame rate of the outputs (default: the video's, else {DEFAULT_FPS:g})")
    p.add_argument("--sync", choices=SYNC_MODES, default="frames",
                   help="how the cameras' frames are paired: 'frames' (frame t of every input "
                   "is one instant; inputs of different frame rates or lengths are refused) "
                   "or 'timestamps' (videos resampled to the first camera's clock: the "
                   "nearest frame of each camera at each of its frame times; the recordings "
                   "must start together) (default: %(default)s)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier run in --out (as a whole set)")
    p.add_argument("--smooth", action=argparse.BooleanOptionalAction, default=None,
                   help="write temporally smoothed poses: a forward-backward (RTS) smoother "
                   "on a constant-velocity model per DOF over the whole run, frames the "
                   "tracker did not keep treated as missing observations (bridged by the "
                   "model; the shirt tracker's own gate, diagnostics column 'gate', else the "
                   "valid flag); valid flags unchanged, poses.npz keeps the per-frame "
                   "estimates as q_raw (default: on for the shirt tracker's learned path, "
                   "where it measured 13.8 -> 9.0 cm on the test split, off otherwise)")
    p.add_argument("--smooth-hz", type=positive_float, metavar="HZ",
                   help=f"with --smooth: the frequency at which the smoother halves a motion's "
                   f"amplitude (response 1/(1+(f/HZ)^4); below half the frame rate) "
                   f"(default: {DEFAULT_CUTOFF_HZ:g})")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--resume", metavar="OUT",
                   help="continue the interrupted run (Ctrl-C, kill -9, disk full, read-only "
                   "folder) that wrote to OUT, from its last checkpoint, with its settings "
                   "(from the journal beside OUT; give no other option but --quiet)")
    p.add_argument("--checkpoint", type=non_negative_seconds, default=CHECKPOINT_EVERY_S,
                   metavar="SECONDS",
                   help="save the tracker's state to the journal at most every SECONDS: at "
                   "most that much tracking is done again after a kill (0: every frame) "
                   "(default: %(default)s)")
    p.add_argument("--tuned", metavar="TUNED_JSON",
                   help="tuned parameters (from `jaxmocap tune`): the shirt tracker's IK "
                   "covariances (generalises --ik-cov) or the stereo filter's cue widths "
                   "sigma_g, sigma_d; refused when made for another tracker, body or shirt")
    from jaxmocap.commands._body import add_body_args

    add_body_args(p)
    g = p.add_argument_group("shirt (--method shirt)")
    g.add_argument("--colors", metavar="COLORS_JSON",
                   help="the shirt's colour model (from `jaxmocap colors`)")
    g.add_argument("--observer", metavar="MODEL_EQX",
                   help="the learned observation model (from `jaxmocap learn` for this body "
                   "and shirt): it classifies the pixels instead of --colors / --white-balance")
    g.add_argument("--white-balance", metavar="WB_JSON",
                   help="initial white balance per camera (`jaxmocap colors --white-balance`); "
                   "default: identity")
    g.add_argument("--db", metavar="DB_NPZ",
                   help="pose database (`jaxmocap build-db --out`); default: the cached "
                   "80,000-pose database, built on first use")
    g.add_argument("--ik-cov", metavar="COV_NPZ",
                   help="IK covariances (.npz, jaxmocap.ik.IKCovariances.save); default: the "
                   "bundled trained ones (jaxmocap.trackers.shirt.trained_covariances)")
    g.add_argument("--work-size", type=int_range(16, 1024, "pixels"), metavar="PX",
                   help="side of the resampled crop the shirt is classified in (default: "
                   "the tracker's, 128)")
    g.add_argument("--validity", choices=tuple(VALIDITY), default=None,
                   help="per-frame validity rule (default: learned on the learned observation, "
                   "paper with --colors): learned (calibrated for the learned observation on "
                   "the test world's dev split: its centroid residual, recall under the model's "
                   "labels and 30 centroids), paper (Wang §5.2) or footage (calibrated on "
                   "footage under spot lamps with clutter: the final pose's centroid residual "
                   "and recall, 26 patch centroids; see docs/USER_GUIDE.md)")
    g = p.add_argument_group("particle filter (--method pf)")
    g.add_argument("--particles", type=int_range(10, MAX_PARTICLES, "compile time grows with "
                                                 "the count"), default=1000,
                   help=f"number of particles, 10..{MAX_PARTICLES:,} (default: %(default)s, "
                   "Azad §V)")
    g.add_argument("--seed", type=int, default=0, help="random seed (default: %(default)s)")
    g.add_argument("--skin", choices=("default", "synth"), default="default",
                   help="fixed HSV skin interval without --pf-colors: default (Azad's), or "
                   "synth for jaxmocap synth scenes (default: %(default)s)")
    g.add_argument("--pf-colors", metavar="PF_COLORS_JSON|auto",
                   help="the capture's skin and shirt colours, recommended for real footage: "
                   "a file from `jaxmocap colors --pf` (scribbled frames of the capture), or "
                   "auto (calibrated from the first 30 frames of the first camera, which are "
                   "not tracked); replaces the fixed HSV intervals and turns on the blob "
                   "plausibility gate and the nearest pairing of the hands")
    g.add_argument("--pf-skin-grow", metavar="PX", type=int_range(0, 20, "a few pixels"),
                   default=0,
                   help="with --pf-colors: grow the skin map by up to PX pixels into a relaxed "
                   "skin map (hysteresis: the shaded rim of small hands; 4 px: better on the "
                   "dev split, not on the test split, docs/results/stereo_pf.md; default: "
                   "%(default)s, off)")
    g.add_argument("--pf-swivel", metavar="FRACTION", type=unit_fraction,
                   help="share of the particles whose arms are turned about their shoulder-hand "
                   "lines each frame (elbow-swivel jumps, beyond Azad; default 0.1); 0 for a "
                   "body whose shoulder is not three x, y, z hinges (e.g. a clavicle + humerus)")
    p.set_defaults(func=run)


def check_stereo_cameras(cams: list[Camera], names: list[str], path: str) -> None:
    """The stereo particle filter's needs: one image size (its blob and edge maps are stacked
    per camera) and two distinct centres (the baseline triangulates the head and hands)."""
    sizes = {(int(c.width), int(c.height)) for c in cams}
    if len(sizes) > 1:
        listing = ", ".join(f"{n} {int(c.width)}x{int(c.height)}"
                            for n, c in zip(names, cams, strict=True))
        raise InputError(f"{path}: --method pf needs cameras of one image size, got {listing}")
    if len(cams) == 2:
        centres = [-np.asarray(c.R, np.float64).T @ np.asarray(c.t, np.float64) for c in cams]
        base = float(np.linalg.norm(centres[0] - centres[1]))
        if not base >= MIN_BASELINE_M:
            raise InputError(f"{path}: cameras {names[0]!r} and {names[1]!r} are {base:.2g} m "
                             f"apart: a stereo pair needs distinct centres (>= "
                             f"{MIN_BASELINE_M * 1e3:g} mm baseline) to triangulate")


OFFSET_PEAK = 0.5  # a motion offset is noted when its correlation is at least this


def _run_json(args, tracked: Tracked, reader: SyncReader, n_frames: int | None) -> str:
    doc = {"format": "jaxmocap.track_run", "version": 1,
           "complete": tracked.interrupted is None, "interrupted_by": tracked.interrupted,
           "frames_written": len(tracked.valid), "frames_tracked": int(tracked.valid.sum()),
           "frames_estimated": int(np.isfinite(tracked.q).all(axis=1).sum()),
           "frames_readable": reader.n_read, "frames_in_input": n_frames,
           "method": args.method,
           "inputs": [str(i) for i in getattr(args, "inputs_given", None) or args.inputs],
           "sync": args.sync, "sync_report": reader.sync_report,
           "smooth_hz": _cutoff(args) if args.smooth else None,
           "motion_offsets": reader.motion_offsets()}
    return json.dumps(doc, indent=2) + "\n"


def _cutoff(args) -> float:
    return DEFAULT_CUTOFF_HZ if args.smooth_hz is None else args.smooth_hz


def _check_smooth(args, fps: float) -> None:
    if args.smooth and not _cutoff(args) < fps / 2:
        raise InputError(f"--smooth-hz {_cutoff(args):g}: must be below half the frame rate "
                         f"({fps:g} fps: < {fps / 2:g} Hz)")


def run(args: argparse.Namespace) -> int:
    quiet_ffmpeg()
    if args.resume:
        args = resumed_args(args)
        if any(str(i).isdigit() and not os.path.exists(i) for i in args.inputs):
            raise InputError(f"--resume {args.resume}: a live capture (camera indices) cannot "
                             "be resumed")
    elif not args.inputs or not args.cameras:
        raise InputError("give the inputs (one video, frame folder or camera index per "
                         "camera) and --cameras CAMERAS_JSON, or --resume OUT")
    if args.smooth is None:  # the learned path's default (docs/results/learned.md)
        args.smooth = _learned_path(args)
    if args.smooth_hz is not None and not args.smooth:
        raise InputError(f"--smooth-hz {args.smooth_hz:g} sets the smoother of --smooth; add "
                         "--smooth")
    if args.method == "pf" and args.observer:
        raise InputError("--observer is read by the shirt tracker (--method shirt); the particle "
                         "filter does not read it yet")
    if args.method == "pf" and args.validity is not None:
        raise InputError(f"--validity {args.validity} is the shirt tracker's rule; the particle "
                         "filter (--method pf) has its own (stereo_pf.frame_validity)")
    out = check_output_folder(args.out)
    formats = [f.strip().lower() for f in args.formats.split(",") if f.strip()]
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise InputError(f"--formats {args.formats!r}: expected a comma-separated subset of "
                         f"{','.join(FORMATS)}")
    names_out = result_names()
    check_outputs([out, *(out / n for n in sorted(names_out))], input_paths(args))
    with output_folder_lock(out):  # one run at a time writes --out
        return _run(args, out, formats, names_out)


def _run(args: argparse.Namespace, out: Path, formats: list[str], names_out: set[str]) -> int:
    resume = bool(args.resume)
    refuse_over_journal(out, args.overwrite, resume)
    # a resumed run replaces what its own interruption wrote there (marked partial)
    stale = check_stale(out, names_out, args.overwrite or resume)
    cams, names = load_cameras(args.cameras)
    real = [os.path.realpath(i) if os.path.exists(i) else i for i in args.inputs]
    dup = next((i for i, r in enumerate(real) if real.index(r) != i), None)
    if dup is not None:
        raise InputError(f"{args.inputs[dup]}: given for two cameras ({real.index(real[dup])} "
                         f"and {dup}); give each camera its own video, frame folder or index")
    if len(args.inputs) != len(cams):
        raise InputError(f"{len(args.inputs)} inputs given for the {len(cams)} cameras of "
                         f"{args.cameras} ({', '.join(names)}); give one input per camera, in "
                         "that order")
    if args.method == "pf":
        check_stereo_cameras(cams, names, args.cameras)
    if args.show and not _has_display():
        raise InputError("--show needs a display and OpenCV with GUI support (no DISPLAY, or "
                         "opencv-python-headless); run without --show (use --overlay to get "
                         "a video of the tracking)")
    with SyncReader(args.inputs, names, [(c.width, c.height) for c in cams],
                    args.max_frames, sync=args.sync) as reader:
        if reader.sync_report:
            print(f"jaxmocap track: {reader.sync_report}")
        fps = args.fps or reader.fps or DEFAULT_FPS
        _check_smooth(args, fps)
        tracker = _make_tracker(args, cams, names)
        journal, restore = open_journal(args, out)
        try:
            return _track_and_write(args, out, formats, stale, reader, tracker, journal,
                                    restore, fps)
        except BaseException as e:
            raise keep_or_drop(journal, e, out, reader.n_read) from None
        finally:
            journal.close()


def _track_and_write(args, out: Path, formats: list[str], stale, reader: SyncReader,
                     tracker: FrameTracker, journal: Journal, restore, fps: float) -> int:
    """The frame loop and the outputs, promoted together; the journal removed once they are
    in place (complete) and kept otherwise."""
    with AtomicFiles(out) as files:
        files.replace_set(stale)
        tracked = track_frames(tracker, reader, files, out, fps, args.overlay,
                               args.show, progress=not args.quiet, journal=journal,
                               restore=restore)
        if reader.n_read == 0:
            raise InputError(f"no readable frames in the inputs: {reader.problems()}")
        # a second Ctrl-C must not leave the set half renamed: the writing is short
        handler = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            names_d = tuple(tracker.diagnostic_names)
            q, extra = tracked.q, {}
            table = diagnostics_table(tracked.rows, names_d)
            if args.smooth:  # the per-frame estimates stay in poses.npz
                weight = (table[:, names_d.index("gate")] > 0 if "gate" in names_d
                          else tracked.valid)  # the shirt's own gate: what its state kept
                q = smooth_poses(tracked.q, weight, fps, _cutoff(args))
                extra["q_raw"] = tracked.q
            track = pose_track(tracker.body, q, tracked.valid, fps, table, names_d)
            write_exports(files, out, tracker.body, track, formats,
                          complete=np.asarray(tracked.interrupted is None),
                          frames_in_input=np.asarray(-1 if reader.n_frames is None
                                                     else reader.n_frames, np.int64),
                          **extra)
            files.path(out / "diagnostics.csv").write_text(
                _diagnostics_csv(names_d, tracked.rows, table))
            files.path(out / "run.json").write_text(
                _run_json(args, tracked, reader, reader.n_frames))
            targets = files.targets
            files.commit()  # while SIGINT is ignored
        finally:
            signal.signal(signal.SIGINT, handler)
    problems = reader.problems()
    if tracked.interrupted is None:
        journal.remove()
    valid = tracked.valid
    summary = (f"tracked {int(valid.sum())} of {len(valid)} frames ({reader.n_read} readable) -> "
               + ", ".join(str(p) for p in targets))
    if tracked.interrupted:
        total = "" if reader.n_frames is None else f" of {reader.n_frames}"
        print(f"PARTIAL: interrupted ({tracked.interrupted}) after {len(valid)}{total} frames; "
              + summary)
        print(f"jaxmocap track: interrupted; wrote the {len(valid)} frames tracked so far, "
              f"marked partial (run.json, poses.npz 'complete'); {journal.where(out)}",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    print(summary)
    offsets = reader.motion_offsets()
    late = [o for o in offsets or () if o["offset_frames"] and o["peak"] >= OFFSET_PEAK]
    if late:
        print("jaxmocap track: note: the cameras' image motion suggests they are not "
              "simultaneous: " + "; ".join(
                  f"{o['camera']} sees it {abs(o['offset_s']) * 1e3:.0f} ms "
                  f"{'later' if o['offset_s'] > 0 else 'earlier'} than {reader.names[0]} "
                  f"(correlation {o['peak']:.2f})" for o in late)
              + "; cut the recordings to a common start (run.json: motion_offsets)")
    if problems:
        print(f"jaxmocap track: warning: {problems}; those frames are NaN in the outputs",
              file=sys.stderr)
        return 1
    return 0
