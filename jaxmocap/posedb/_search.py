"""Querying the pose database: the id-map distance, exact and fast 10-NN, the blended pose
(Wang et al. 2011 §5.2, Step 2; the distance follows Wang & Popović 2009).

**Distance.** Tiny maps hold colour ids, ``0`` for background *or an unclassified pixel* (a
classified camera crop cannot tell them apart). Between two maps ``r, r'``

    d(r, r') = sum_p c(r_p, r'_p),   c(a, b) = 0 if a == b,  1 if a != b are both shirt
                                     colours,  1/2 if exactly one of them is 0.

A wrong colour says much more about the pose (a crossed arm, a turned torso) than a pixel on
the silhouette's border that a small shift or a missed classification flips, so background
mismatches count half (``BACKGROUND_WEIGHT``). With this weight ``d`` is exactly a squared
Euclidean distance, ``d = 1/2 ||E(r) - E(r')||^2`` where ``E`` one-hot encodes every pixel's
colour and maps background to the zero vector; the fast search below relies on it.

**Exact search** (the reference). Maps are packed once into 4-bit codes, eight pixels per
``uint32`` word (200 words), plus a 1-bit silhouette (52 words). For a query code ``c`` and a
database code ``a``, a nibble of ``x = a ^ c`` is nonzero iff the pixel differs; folding the
nibble's bits (``x | x >> 1 | x >> 2``) and summing nibbles counts ``n_diff``, and the popcount
of the silhouettes' XOR counts the colour/background mismatches ``n_sil``, so
``2 d = 2 n_diff - n_sil``: integer operations on 1 KB per pose, no one-hot vectors. The
database is stored word-major in chunks, ``(n_chunks, 252, chunk)``; each chunk's distances
accumulate word by word (a ``fori_loop``, vectorised across the chunk's poses), its ``k`` best
are kept and the chunks' winners merged. Ties go to the lower database index everywhere.

**Fast search** (coarse-to-fine, no extra memory). The pixels are packed in polyphase order:
first the quarter-resolution grid of even rows and even columns (50 nibble words + 13
silhouette words), then the odd/odd, even/odd and odd/even grids. The distance restricted to
the first ``phases`` grids is an unbiased estimate of ``phases / 4`` times the full one; it
is computed over the whole database from the leading words only (a quarter of the memory
traffic for ``phases = 1``), its ``N_CANDIDATES`` best are re-ranked with the full distance.
(Coarse colour histograms, the other classic compact descriptor — 10 colours in an 8x8 grid,
640 floats per pose, ranked by one GEMV — recall the exact neighbours far less often: see
benchmarks/bench_posedb.py.)

**Blend.** The pose estimate ``q_b`` weighs the neighbours' poses ``q^i`` by a Gaussian of how
much farther they are than the best, ``w_i ∝ exp(-(d_i - d_1)^2 / (2 sigma^2))``: joint angles
(and the root translation) linearly; root rotations as the normalised weighted sum of their
unit quaternions, signs aligned with the best one's (the chordal mean around the best).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float, Int, Integer, UInt8, UInt32

from ..body import ROOT_DOFS
from ..errors import InputError
from ..render import TINY_SIZE, resample_ids, window_from_mask
from ..rotations import quat_to_rotvec

K_NEIGHBOURS = 10  # Wang et al. §5.2: "the ten nearest neighbors"
BACKGROUND_WEIGHT = 0.5  # cost of a colour/background mismatch (module docstring)
PIXELS = TINY_SIZE * TINY_SIZE
PHASES = 4  # polyphase grids (even/odd rows x even/odd columns)
PHASE_PIXELS = PIXELS // PHASES
PHASE_NIBBLE_WORDS = PHASE_PIXELS // 8  # 4-bit colour codes, 8 per uint32
PHASE_SIL_WORDS = -(-PHASE_PIXELS // 32)  # 1-bit silhouette, 32 per uint32 (zero-padded)
NIBBLE_WORDS = PHASES * PHASE_NIBBLE_WORDS
SIL_WORDS = PHASES * PHASE_SIL_WORDS
CODE_WORDS = NIBBLE_WORDS + SIL_WORDS
MAX_COLOURS = 15  # colour ids must fit in 4 bits
N_CANDIDATES = 200  # candidates of the fast search re-ranked exactly
COARSE_PHASES = 1  # grids of the fast search's first stage (1: quarter resolution)
SEARCH_CHUNK = 8192  # database poses per chunk of the exact search
BLEND_SIGMA = 16.0  # pixels; 8-32 within 0.4 cm of each other on bench_posedb held-out queries
_UNROLL = 4


class DatabaseError(InputError):
    """A pose database (arrays or file) that does not have the expected content."""


class Neighbours(NamedTuple):
    """The k nearest database poses: indices and distances ``d`` (pixels, module doc),
    sorted by increasing distance, ties by increasing index."""

    index: Int[Array, " k"]
    distance: Float[Array, " k"]


class PoseDB(eqx.Module):
    """A pose database ready to query: poses and packed maps.

    ``poses[i]`` (n, n_dof) is pose ``q^i`` in the canonical world (root at the origin, see
    :mod:`jaxmocap.posedb`); ``codes[c, :, j]`` the packed map of pose ``c * chunk + j``
    (module docstring; padding columns are never returned).
    """

    poses: Float[Array, "n n_dof"]
    codes: UInt32[Array, "c w chunk"]
    n_colours: int = eqx.field(static=True)
    key: str = eqx.field(static=True, default="")

    @property
    def size(self) -> int:
        return self.poses.shape[0]

    @property
    def chunk(self) -> int:
        return self.codes.shape[2]


# ----------------------------------------------------------------------------- codes


def _polyphase_order() -> np.ndarray:
    """Pixel indices (row-major) in polyphase order: grids (even, even), (odd, odd),
    (even, odd), (odd, even), each row-major."""
    i, j = np.meshgrid(np.arange(TINY_SIZE), np.arange(TINY_SIZE), indexing="ij")
    flat = i * TINY_SIZE + j
    return np.concatenate([flat[a::2, b::2].ravel() for a, b in ((0, 0), (1, 1), (0, 1), (1, 0))])


POLYPHASE = _polyphase_order()


def pack_map(tiny: Integer[Array, "n n"]) -> UInt32[Array, " w"]:
    """Packed code of one tiny map (pixels in :data:`POLYPHASE` order): 200 words of 4-bit
    colours (pixel ``p`` of phase ``g`` in word ``50 g + p // 8`` at bit ``4 (p % 8)``), then
    52 words of silhouette bits (13 per phase, pixel ``p`` at bit ``p % 32`` of word
    ``13 g + p // 32``)."""
    v = tiny.reshape(-1)[POLYPHASE].astype(jnp.uint32)
    nib = v.reshape(NIBBLE_WORDS, 8) << (4 * jnp.arange(8, dtype=jnp.uint32))[None]
    fg = (v > 0).astype(jnp.uint32).reshape(PHASES, PHASE_PIXELS)
    fg = jnp.pad(fg, ((0, 0), (0, PHASE_SIL_WORDS * 32 - PHASE_PIXELS)))
    sil = fg.reshape(SIL_WORDS, 32) << jnp.arange(32, dtype=jnp.uint32)[None]
    return jnp.concatenate([jnp.sum(nib, axis=1, dtype=jnp.uint32),
                            jnp.sum(sil, axis=1, dtype=jnp.uint32)])


def unpack_codes(db: PoseDB) -> UInt8[np.ndarray, "n s s"]:
    """The database's tiny maps (n, 40, 40) ``uint8`` recovered from its packed codes."""
    words = np.asarray(db.codes)[:, :NIBBLE_WORDS, :].transpose(0, 2, 1)
    words = words.reshape(-1, NIBBLE_WORDS)[: db.size]
    nibbles = (words[:, :, None] >> (4 * np.arange(8, dtype=np.uint32))) & 15
    maps = np.zeros((db.size, PIXELS), np.uint8)
    maps[:, POLYPHASE] = nibbles.reshape(db.size, PIXELS)
    return maps.reshape(-1, TINY_SIZE, TINY_SIZE)


def _fold(x: Array) -> Array:
    """Bit ``4 j`` of the result is set iff nibble ``j`` of ``x`` is nonzero."""
    t = x | (x >> 1)
    t = t | (t >> 2)
    return t & jnp.uint32(0x11111111)


def _nibble_sum(f: Array) -> Array:
    """Sum of the eight 0/1 nibbles of ``f`` (the top nibble of ``f * 0x11111111``)."""
    return ((f * jnp.uint32(0x11111111)) >> 28).astype(jnp.int32)


def _chunk_distances(
    codes: UInt32[Array, "w c"], q: UInt32[Array, " w"], phases: int = PHASES
) -> Int[Array, " c"]:
    """``2 d`` (over the first ``phases`` polyphase grids) between the query code and every
    column of a word-major chunk."""
    zero = jnp.zeros(codes.shape[1], jnp.int32)

    def nib(i, acc):
        return acc + _nibble_sum(_fold(codes[i] ^ q[i]))

    def sil(i, acc):
        j = NIBBLE_WORDS + i
        return acc + lax.population_count(codes[j] ^ q[j]).astype(jnp.int32)

    n_diff = lax.fori_loop(0, phases * PHASE_NIBBLE_WORDS, nib, zero, unroll=_UNROLL)
    n_sil = lax.fori_loop(0, phases * PHASE_SIL_WORDS, sil, zero, unroll=_UNROLL)
    return 2 * n_diff - n_sil


def _row_distances(codes: UInt32[Array, "m w"], q: UInt32[Array, " w"]) -> Int[Array, " m"]:
    """``2 d`` between the query code and a few codes stored row-major."""
    x = codes ^ q[None]
    n_diff = jnp.sum(_nibble_sum(_fold(x[:, :NIBBLE_WORDS])), axis=1)
    n_sil = jnp.sum(lax.population_count(x[:, NIBBLE_WORDS:]).astype(jnp.int32), axis=1)
    return 2 * n_diff - n_sil


def map_distance(a: Integer[Array, "n n"], b: Integer[Array, "n n"]) -> Float[Array, ""]:
    """The distance ``d(a, b)`` of the module docstring, directly on two id maps."""
    fg_a, fg_b = a > 0, b > 0
    colour = jnp.sum((a != b) & fg_a & fg_b)
    sil = jnp.sum(fg_a != fg_b)
    return (colour + BACKGROUND_WEIGHT * sil).astype(jnp.float32)


def _check_query(db: PoseDB, tiny: Array, k: int) -> None:
    if tiny.shape != (TINY_SIZE, TINY_SIZE):
        raise ValueError(f"pose database query: expected a ({TINY_SIZE}, {TINY_SIZE}) id map, "
                         f"got shape {tiny.shape}")
    if not 1 <= k <= db.size:
        raise ValueError(f"pose database query: k = {k} must lie in 1..{db.size}")


def _all_distances(db: PoseDB, q: Array, phases: int, k: int) -> tuple[Array, Array]:
    """The ``k`` smallest ``2 d`` (as negated float32) and their indices, chunk by chunk."""
    n, chunk = db.size, db.chunk
    kc = min(k, chunk)
    offsets = jnp.arange(db.codes.shape[0], dtype=jnp.int32) * chunk

    def one(args):
        codes, offset = args
        d2 = _chunk_distances(codes, q, phases).astype(jnp.float32)
        idx = offset + jnp.arange(chunk, dtype=jnp.int32)
        v, i = lax.top_k(-jnp.where(idx < n, d2, jnp.inf), kc)
        return v, idx[i]

    v, i = lax.map(one, (db.codes, offsets))
    v, j = lax.top_k(v.reshape(-1), k)
    return v, i.reshape(-1)[j]


@eqx.filter_jit
def query_exact(db: PoseDB, tiny: Integer[Array, "n n"], k: int = K_NEIGHBOURS) -> Neighbours:
    """The ``k`` nearest database maps of the tiny id map ``tiny`` (40x40 colour ids), exactly:
    brute force over the packed codes, chunk by chunk (module docstring). jit/vmap."""
    _check_query(db, tiny, k)
    v, i = _all_distances(db, pack_map(tiny), PHASES, k)
    return Neighbours(index=i, distance=-v / 2)


@eqx.filter_jit
def query_fast(
    db: PoseDB,
    tiny: Integer[Array, "n n"],
    k: int = K_NEIGHBOURS,
    candidates: int = N_CANDIDATES,
    phases: int = COARSE_PHASES,
) -> Neighbours:
    """The ``k`` nearest database maps of ``tiny``, coarse to fine: the ``candidates`` nearest
    on the first ``phases`` polyphase grids, re-ranked with the full distance (module
    docstring). Equals :func:`query_exact` whenever the exact neighbours are among the
    candidates. jit/vmap."""
    _check_query(db, tiny, k)
    if not 1 <= phases <= PHASES:
        raise ValueError(f"query_fast: phases = {phases} must lie in 1..{PHASES}")
    q = pack_map(tiny)
    _, cand = _all_distances(db, q, phases, min(max(candidates, k), db.size))
    cand = jnp.sort(cand)  # ties of the exact distance go to the lower index
    codes = db.codes[cand // db.chunk, :, cand % db.chunk]
    d2 = _row_distances(codes, q).astype(jnp.float32)
    v, j = lax.top_k(-d2, k)
    return Neighbours(index=cand[j], distance=-v / 2)


# ----------------------------------------------------------------------------- blend


def rotvec_to_quat(w: Float[Array, "*b 3"]) -> Float[Array, "*b 4"]:
    """Unit quaternion ``(cos(theta/2), sin(theta/2) w/theta)`` of a rotation vector;
    NaN-free at ``w = 0``."""
    t2 = jnp.sum(w * w, axis=-1)
    small = t2 < jnp.sqrt(jnp.finfo(w.dtype).eps)
    t = jnp.sqrt(jnp.where(small, jnp.ones_like(t2), t2))
    half = jnp.where(small, 0.5 - t2 / 48.0, jnp.sin(t / 2) / t)
    c = jnp.where(small, 1.0 - t2 / 8.0, jnp.cos(t / 2))
    return jnp.concatenate([c[..., None], w * half[..., None]], axis=-1)


def blend_poses(
    poses: Float[Array, "k n_dof"], distance: Float[Array, " k"], sigma: float = BLEND_SIGMA
) -> Float[Array, " n_dof"]:
    """Weighted blend ``q_b`` of neighbour poses sorted by distance (module docstring):
    ``w_i ∝ exp(-(d_i - d_1)^2 / (2 sigma^2))``; joint angles and root translation linearly,
    root rotations by the sign-aligned normalised quaternion sum. Follows ``poses.dtype``."""
    dt = poses.dtype
    d = distance.astype(dt)
    w = jnp.exp(-0.5 * ((d - d[0]) / sigma) ** 2)
    w = w / jnp.sum(w)
    lin = jnp.sum(w[:, None] * poses, axis=0)
    quats = rotvec_to_quat(poses[:, 3:6])
    sign = jnp.where(quats @ quats[0] < 0, -1.0, 1.0).astype(dt)
    qbar = jnp.sum((w * sign)[:, None] * quats, axis=0)
    rot = quat_to_rotvec(qbar / jnp.linalg.norm(qbar))
    return jnp.concatenate([lin[:3], rot, lin[ROOT_DOFS:]])


def blend(db: PoseDB, neighbours: Neighbours, sigma: float = BLEND_SIGMA) -> Float[Array, " n_dof"]:
    """The blended pose ``q_b`` of ``neighbours`` (canonical world; see
    :func:`jaxmocap.posedb.pose_in_camera` for a real camera's world)."""
    return blend_poses(db.poses[neighbours.index], neighbours.distance, sigma)


@eqx.filter_jit
def estimate_pose(
    db: PoseDB,
    tiny: Integer[Array, "n n"],
    k: int = K_NEIGHBOURS,
    sigma: float | Float[Array, ""] = BLEND_SIGMA,
    exact: bool = False,
) -> tuple[Float[Array, " n_dof"], Neighbours]:
    """Wang et al. §5.2 Step 2: the ``k`` nearest neighbours of the classified tiny map and
    their blend ``q_b`` (canonical world). ``exact`` picks the brute-force search."""
    nb = query_exact(db, tiny, k) if exact else query_fast(db, tiny, k)
    return blend(db, nb, sigma), nb


# Not in the paper: orientation hypotheses (issue 38 item 2). Side and back views are
# ambiguous in a tiny map (the far arm hidden; the two patches of a colour on the front and the
# back), so the nearest neighbours can disagree about which way the body faces, and one blend
# of them averages orientations and the arms of different views.
N_HYPOTHESES = 3  # orientation clusters returned by estimate_hypotheses
HYPOTHESIS_NEIGHBOURS = 30  # nearest maps split into the clusters
CLUSTER_ANGLE = 0.7854  # rad (45 deg): a neighbour joins a cluster within this of its seed


def _masked_blend(poses: Array, distance: Array, member: Array, sigma) -> Array:
    """:func:`blend_poses` over the ``member`` rows only (at most ``K_NEIGHBOURS`` of them,
    the nearest first), weights relative to the nearest member, quaternion signs aligned with
    it; the rows are sorted by distance."""
    dt = poses.dtype
    member = member & (jnp.cumsum(member) <= K_NEIGHBOURS)
    first = jnp.argmax(member)
    d = distance.astype(dt)
    w = jnp.where(member, jnp.exp(-0.5 * ((d - d[first]) / sigma) ** 2), 0.0)
    w = w / jnp.maximum(jnp.sum(w), jnp.finfo(dt).tiny)
    lin = jnp.sum(w[:, None] * poses, axis=0)
    quats = rotvec_to_quat(poses[:, 3:6])
    sign = jnp.where(quats @ quats[first] < 0, -1.0, 1.0).astype(dt)
    qbar = jnp.sum((w * sign)[:, None] * quats, axis=0)
    qbar = jnp.where(jnp.linalg.norm(qbar) > 0, qbar, quats[first])
    rot = quat_to_rotvec(qbar / jnp.linalg.norm(qbar))
    return jnp.concatenate([lin[:3], rot, lin[ROOT_DOFS:]])


class Hypotheses(NamedTuple):
    """Orientation hypotheses of one query (:func:`estimate_hypotheses`): ``poses`` (H, n_dof)
    blended per cluster, canonical world, nearest cluster first; ``distance`` (H,) the map
    distance of each cluster's seed (``inf`` where the neighbours held fewer clusters: the
    pose then repeats the first)."""

    poses: Float[Array, "h n_dof"]
    distance: Float[Array, " h"]


@eqx.filter_jit
def estimate_hypotheses(
    db: PoseDB,
    tiny: Integer[Array, "n n"],
    n_hyp: int = N_HYPOTHESES,
    k: int = HYPOTHESIS_NEIGHBOURS,
    angle: float = CLUSTER_ANGLE,
    sigma: float | Float[Array, ""] = BLEND_SIGMA,
) -> Hypotheses:
    """Step 2 with the orientations kept apart (issue 38 item 2): the ``k`` nearest maps of
    ``tiny`` (:func:`query_fast`) split greedily into orientation clusters -- the nearest
    neighbour not yet within ``angle`` (root rotation, geodesic) of an earlier cluster's seed
    seeds the next -- and each cluster's (up to ``K_NEIGHBOURS``) nearest members blended
    (:func:`blend_poses`'s weights and rotation mean). ``n_hyp`` clusters at most, nearest
    seed first; the first is the blend of the nearest neighbour's orientation, so with one
    orientation among the neighbours it is the 10-NN blend. jit/vmap."""
    _check_query(db, tiny, k)
    nb = query_fast(db, tiny, k)
    poses = db.poses[nb.index]
    quats = rotvec_to_quat(poses[:, 3:6])
    cos_half = jnp.cos(jnp.asarray(angle, poses.dtype) / 2)
    near = jnp.abs(quats @ quats.T) >= cos_half  # (k, k): within ``angle`` of each other
    taken = jnp.zeros(k, bool)
    out, dist = [], []
    for _ in range(n_hyp):
        free = ~taken
        seed = jnp.argmax(free)
        ok = jnp.any(free)
        member = near[seed] & free
        q = _masked_blend(poses, nb.distance, member, sigma)
        out.append(q), dist.append(jnp.where(ok, nb.distance[seed], jnp.inf))
        taken = taken | (near[seed] & ok)
    poses_h = jnp.stack(out)
    dist = jnp.stack(dist)
    poses_h = jnp.where(jnp.isfinite(dist)[:, None], poses_h, poses_h[0][None])
    return Hypotheses(poses_h, dist)


def tiny_from_classified(ids: Integer[Array, "h w"]) -> Int[Array, "n n"]:
    """A classified crop (colour ids, 0 = background/unclassified) normalised to the tiny
    40x40 map the same way the database's maps are (:mod:`jaxmocap.render`)."""
    return resample_ids(ids, window_from_mask(ids > 0))


# ----------------------------------------------------------------------------- construction


@jax.jit
def _pack_batch(maps: Array) -> Array:
    return jax.vmap(pack_map)(maps).T


def make_posedb(
    maps: np.ndarray | Array,
    poses: np.ndarray | Array,
    n_colours: int,
    key: str = "",
    chunk: int = SEARCH_CHUNK,
) -> PoseDB:
    """Pack ``maps`` (n, 40, 40) ``uint8`` into a queryable :class:`PoseDB` with chunks of
    ``chunk`` poses (rounded to the database size); ``poses`` (n, n_dof) are stored float32."""
    maps = np.asarray(maps)
    poses = np.asarray(poses)
    if maps.ndim != 3 or maps.shape[1:] != (TINY_SIZE, TINY_SIZE) or maps.dtype != np.uint8:
        raise DatabaseError(f"pose database maps: expected uint8 (n, {TINY_SIZE}, {TINY_SIZE}), "
                            f"got {maps.dtype} {maps.shape}")
    n = maps.shape[0]
    if n == 0 or poses.ndim != 2 or poses.shape[0] != n:
        raise DatabaseError(f"pose database poses: expected ({n} >= 1, n_dof), got {poses.shape}")
    if not 1 <= n_colours <= MAX_COLOURS or int(maps.max()) > n_colours:
        raise DatabaseError(f"pose database maps: colour ids must lie in 0..{n_colours} "
                            f"(at most {MAX_COLOURS} colours), found {int(maps.max())}")
    chunk = int(min(chunk, -(-n // 256) * 256))
    n_pad = -(-n // chunk) * chunk
    padded = np.zeros((n_pad, TINY_SIZE, TINY_SIZE), np.uint8)
    padded[:n] = maps
    codes = [np.asarray(_pack_batch(jnp.asarray(padded[s:s + chunk])))
             for s in range(0, n_pad, chunk)]
    return PoseDB(poses=jnp.asarray(poses.astype(np.float32)), codes=jnp.asarray(np.stack(codes)),
                  n_colours=int(n_colours), key=key)
